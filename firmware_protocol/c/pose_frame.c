/* Reference decoder for the vlp-agent pose frame; see pose_frame.h and docs/wire-format.md. */
#include "pose_frame.h"

uint16_t pose_crc16_ccitt_false(const uint8_t *data, size_t len)
{
    /* Bitwise: 8 shifts per byte, no table in flash. unsigned is at least 16 bits; the mask keeps 16. */
    unsigned crc = 0xFFFFu;
    size_t i;
    unsigned bit;

    for (i = 0; i < len; i++) {
        crc ^= (unsigned)data[i] << 8;
        for (bit = 0; bit < 8u; bit++) {
            crc = ((crc & 0x8000u) ? ((crc << 1) ^ 0x1021u) : (crc << 1)) & 0xFFFFu;
        }
    }
    return (uint16_t)crc;
}

/* Little-endian reads that do not depend on the host's byte order or alignment. */
static uint16_t get_u16(const uint8_t *p)
{
    return (uint16_t)(p[0] | ((uint16_t)p[1] << 8));
}

static uint32_t get_u32(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}

static uint64_t get_u64(const uint8_t *p)
{
    return (uint64_t)get_u32(p) | ((uint64_t)get_u32(p + 4) << 32);
}

/* Two's complement without implementation-defined conversions. */
static int32_t get_i32(const uint8_t *p)
{
    uint32_t u = get_u32(p);
    return (u <= 0x7FFFFFFFu) ? (int32_t)u : (int32_t)(u - 0x80000000u) - 0x7FFFFFFF - 1;
}

static int16_t get_i16(const uint8_t *p)
{
    uint16_t u = get_u16(p);
    return (u <= 0x7FFFu) ? (int16_t)u : (int16_t)((int32_t)u - 0x10000);
}

pose_status_t pose_frame_parse(const uint8_t *decoded, size_t len, pose_frame_t *out)
{
    size_t payload_len;
    uint8_t major;
    uint8_t minor;

    /* Same order as the Python decoder: length bounds, CRC, version, length for the version. */
    if (len < POSE_FRAME_PAYLOAD_LEN + POSE_FRAME_CRC_LEN || len > POSE_FRAME_MAX_DECODED_LEN) {
        return POSE_ERR_LENGTH;
    }
    payload_len = len - POSE_FRAME_CRC_LEN;
    if (pose_crc16_ccitt_false(decoded, payload_len) != get_u16(decoded + payload_len)) {
        return POSE_ERR_CRC;
    }
    major = (uint8_t)(decoded[0] >> 4);
    minor = (uint8_t)(decoded[0] & 0x0Fu);
    if (major != POSE_FRAME_VERSION_MAJOR) {
        return POSE_ERR_VERSION;
    }
    if (minor == 0u && payload_len != POSE_FRAME_PAYLOAD_LEN) {
        return POSE_ERR_LENGTH;
    }
    /* A later minor version appends fields after byte 30: they are ignored here. */
    out->version = decoded[0];
    out->reset_counter = decoded[1];
    out->flags = get_u16(decoded + 2);
    out->sequence = get_u32(decoded + 4);
    out->t_us = get_u64(decoded + 8);
    out->x = get_i32(decoded + 16);
    out->y = get_i32(decoded + 20);
    out->yaw = get_i16(decoded + 24);
    out->sigma_xy = get_u16(decoded + 26);
    out->sigma_yaw = get_u16(decoded + 28);
    return POSE_OK;
}

void pose_decoder_reset(pose_decoder_t *dec)
{
    dec->len = 0;
    dec->block_left = 0;
    dec->zero_pending = 0;
    dec->overflow = 0;
    dec->raw_len = 0;
}

void pose_decoder_init(pose_decoder_t *dec)
{
    pose_decoder_reset(dec);
    dec->last_error = POSE_OK;
    dec->stats.frames = 0;
    dec->stats.crc_errors = 0;
    dec->stats.length_errors = 0;
    dec->stats.cobs_errors = 0;
    dec->stats.version_errors = 0;
    dec->stats.overflows = 0;
    dec->stats.discarded_bytes = 0;
}

int cobs_unstuff_byte(uint8_t byte, uint8_t *buf, uint8_t cap, uint8_t *len, uint8_t *block_left,
                      uint8_t *zero_pending)
{
    if (*block_left == 0u) {
        /* A COBS code byte: the previous block (if any, and if shorter than 254) ended in a zero. */
        if (*zero_pending) {
            if (*len >= cap) {
                return 1;
            }
            buf[(*len)++] = 0u;
        }
        *block_left = (uint8_t)(byte - 1u);
        *zero_pending = (uint8_t)(byte != 0xFFu);
        return 0;
    }
    if (*len >= cap) {
        return 1;
    }
    buf[(*len)++] = byte;
    (*block_left)--;
    return 0;
}

static void reject(pose_decoder_t *dec, pose_status_t why)
{
    switch (why) {
    case POSE_ERR_COBS:
        dec->stats.cobs_errors++;
        break;
    case POSE_ERR_LENGTH:
        dec->stats.length_errors++;
        break;
    case POSE_ERR_CRC:
        dec->stats.crc_errors++;
        break;
    case POSE_ERR_VERSION:
        dec->stats.version_errors++;
        break;
    case POSE_ERR_OVERFLOW: /* counted when it happened */
    case POSE_OK:
    default:
        break;
    }
    if (why != POSE_ERR_OVERFLOW) {
        dec->last_error = why;
    }
    dec->stats.discarded_bytes += dec->raw_len + 1u;
}

int pose_decoder_feed(pose_decoder_t *dec, uint8_t byte, pose_frame_t *out)
{
    pose_status_t status;

    if (byte == 0u) {
        if (dec->raw_len == 0u) {
            return 0; /* idle fill between frames */
        }
        if (dec->overflow) {
            status = POSE_ERR_OVERFLOW;
        } else if (dec->block_left != 0u) {
            status = POSE_ERR_COBS;
        } else {
            /* The last block's implied zero is the delimiter itself: zero_pending is dropped. */
            status = pose_frame_parse(dec->buf, dec->len, out);
        }
        if (status == POSE_OK) {
            dec->stats.frames++;
        } else {
            reject(dec, status);
        }
        pose_decoder_reset(dec);
        return status == POSE_OK;
    }

    if (dec->raw_len < 0xFFFFFFFFu) {
        dec->raw_len++;
    }
    if (dec->overflow) {
        return 0;
    }
    if (cobs_unstuff_byte(byte, dec->buf, POSE_FRAME_MAX_DECODED_LEN, &dec->len, &dec->block_left,
                          &dec->zero_pending)) {
        dec->overflow = 1;
        dec->stats.overflows++;
        dec->last_error = POSE_ERR_OVERFLOW;
    }
    return 0;
}
