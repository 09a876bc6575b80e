/* Reference command encoders and goal-status decoder; see command_frame.h and docs/wire-format.md. */
#include "command_frame.h"

#include "pose_frame.h"

static void put_u16(uint8_t *p, uint16_t v)
{
    p[0] = (uint8_t)(v & 0xFFu);
    p[1] = (uint8_t)(v >> 8);
}

static void put_u32(uint8_t *p, uint32_t v)
{
    put_u16(p, (uint16_t)(v & 0xFFFFu));
    put_u16(p + 2, (uint16_t)(v >> 16));
}

/* Two's complement bit patterns without implementation-defined conversions. */
static uint16_t bits16(int16_t v)
{
    return (v >= 0) ? (uint16_t)v : (uint16_t)(0x10000 + (int32_t)v);
}

static uint32_t bits32(int32_t v)
{
    return (v >= 0) ? (uint32_t)v : (uint32_t)(0xFFFFFFFFu - (uint32_t)(-(v + 1)));
}

static uint16_t get_u16(const uint8_t *p)
{
    return (uint16_t)(p[0] | ((uint16_t)p[1] << 8));
}

/* COBS(payload || CRC-LE) || 0x00 into out; payload_len + 2 < 254, so there is one code byte per zero. */
static size_t frame(uint8_t *out, uint8_t *payload, size_t payload_len)
{
    uint16_t crc = pose_crc16_ccitt_false(payload, payload_len);
    size_t n = payload_len + 2u;
    size_t code_at = 0u;
    size_t o = 1u;
    size_t i;

    put_u16(payload + payload_len, crc);
    for (i = 0; i < n; i++) {
        if (payload[i] == 0u) {
            out[code_at] = (uint8_t)(o - code_at);
            code_at = o++;
        } else {
            out[o++] = payload[i];
        }
    }
    out[code_at] = (uint8_t)(o - code_at);
    out[o++] = 0u;
    return o;
}

static void header(uint8_t *p, uint8_t type, uint16_t sequence)
{
    p[0] = type;
    p[1] = CMD_FRAME_VERSION;
    put_u16(p + 2, sequence);
}

size_t cmd_encode_velocity(uint8_t *out, uint16_t sequence, int16_t v_mm_s, int16_t omega_mrad_s,
                           uint16_t timeout_ms)
{
    uint8_t p[10 + 2];
    header(p, CMD_TYPE_VELOCITY, sequence);
    put_u16(p + 4, bits16(v_mm_s));
    put_u16(p + 6, bits16(omega_mrad_s));
    put_u16(p + 8, timeout_ms);
    return frame(out, p, 10u);
}

size_t cmd_encode_goal(uint8_t *out, const cmd_goal_t *goal)
{
    uint8_t p[22 + 2];
    header(p, CMD_TYPE_GOAL, goal->sequence);
    put_u16(p + 4, goal->goal_id);
    p[6] = goal->options;
    p[7] = 0u;
    put_u32(p + 8, bits32(goal->x));
    put_u32(p + 12, bits32(goal->y));
    put_u16(p + 16, (goal->options & CMD_GOAL_OPTION_YAW) ? bits16(goal->yaw) : 0u);
    put_u16(p + 18, goal->tolerance_xy);
    put_u16(p + 20, goal->tolerance_yaw);
    return frame(out, p, 22u);
}

size_t cmd_encode_cancel(uint8_t *out, uint16_t sequence, uint16_t goal_id)
{
    uint8_t p[6 + 2];
    header(p, CMD_TYPE_CANCEL, sequence);
    put_u16(p + 4, goal_id);
    return frame(out, p, 6u);
}

size_t cmd_encode_stop(uint8_t *out, uint16_t sequence)
{
    uint8_t p[4 + 2];
    header(p, CMD_TYPE_STOP, sequence);
    return frame(out, p, 4u);
}

size_t cmd_encode_resume(uint8_t *out, uint16_t sequence)
{
    uint8_t p[4 + 2];
    header(p, CMD_TYPE_RESUME, sequence);
    return frame(out, p, 4u);
}

size_t cmd_encode_follow(uint8_t *out, uint16_t sequence, uint16_t follow_id, uint8_t action,
                         const uint8_t *tag, size_t tag_len)
{
    uint8_t p[24 + 2];
    size_t i;

    if (action > CMD_FOLLOW_STOP || tag_len > CMD_FOLLOW_TAG_MAX_LEN || (tag_len != 0u && tag == NULL) ||
        (action == CMD_FOLLOW_STOP && tag_len != 0u)) {
        return 0u;
    }
    header(p, CMD_TYPE_FOLLOW, sequence);
    p[1] = CMD_FRAME_VERSION_FOLLOW;
    put_u16(p + 4, follow_id);
    p[6] = action;
    p[7] = (uint8_t)tag_len;
    for (i = 0; i < CMD_FOLLOW_TAG_MAX_LEN; i++) {
        p[8 + i] = (i < tag_len) ? tag[i] : 0u;
    }
    return frame(out, p, 24u);
}

#define STATUS_PAYLOAD_LEN 12u

status_result_t goal_status_parse(const uint8_t *decoded, size_t len, goal_status_t *out)
{
    size_t payload_len;

    /* Same order as the Python codec: length bounds, CRC, type, version, length for the version. */
    if (len < 4u + 2u || len > CMD_FRAME_MAX_DECODED_LEN) {
        return STATUS_ERR_LENGTH;
    }
    payload_len = len - 2u;
    if (pose_crc16_ccitt_false(decoded, payload_len) != get_u16(decoded + payload_len)) {
        return STATUS_ERR_CRC;
    }
    if ((decoded[0] >> 4) == 1u) {
        return STATUS_POSE;
    }
    if (decoded[0] != CMD_TYPE_GOAL_STATUS) {
        return STATUS_ERR_TYPE;
    }
    if ((decoded[1] >> 4) != (CMD_FRAME_VERSION >> 4)) {
        return STATUS_ERR_VERSION;
    }
    if (((decoded[1] & 0x0Fu) == 0u && payload_len != STATUS_PAYLOAD_LEN) ||
        payload_len < STATUS_PAYLOAD_LEN || payload_len > CMD_FRAME_MAX_PAYLOAD_LEN) {
        return STATUS_ERR_LENGTH;
    }
    if (decoded[8] > GOAL_CANCELLED) {
        return STATUS_ERR_VALUE;
    }
    out->version = decoded[1];
    out->sequence = get_u16(decoded + 2);
    out->command_sequence = get_u16(decoded + 4);
    out->goal_id = get_u16(decoded + 6);
    out->state = decoded[8];
    out->reason = (decoded[9] > REASON_LAST) ? (uint8_t)REASON_NONE : decoded[9];
    out->remaining = get_u16(decoded + 10);
    return STATUS_OK;
}

static void restart(status_decoder_t *dec)
{
    dec->len = 0;
    dec->block_left = 0;
    dec->zero_pending = 0;
    dec->overflow = 0;
    dec->raw_len = 0;
}

void status_decoder_init(status_decoder_t *dec)
{
    status_decoder_stats_t zero = {0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u};
    restart(dec);
    dec->stats = zero;
}

int status_decoder_feed(status_decoder_t *dec, uint8_t byte, goal_status_t *out)
{
    status_result_t result;

    if (byte == 0u) {
        if (dec->raw_len == 0u) {
            return 0; /* idle fill */
        }
        if (dec->overflow) {
            result = STATUS_ERR_OVERFLOW; /* counted when it happened */
        } else if (dec->block_left != 0u) {
            result = STATUS_ERR_COBS;
        } else {
            result = goal_status_parse(dec->buf, dec->len, out);
        }
        switch (result) {
        case STATUS_OK: dec->stats.frames++; break;
        case STATUS_POSE: dec->stats.pose_frames++; break;
        case STATUS_ERR_COBS: dec->stats.cobs_errors++; break;
        case STATUS_ERR_LENGTH: dec->stats.length_errors++; break;
        case STATUS_ERR_CRC: dec->stats.crc_errors++; break;
        case STATUS_ERR_TYPE: dec->stats.type_errors++; break;
        case STATUS_ERR_VERSION: dec->stats.version_errors++; break;
        case STATUS_ERR_VALUE: dec->stats.value_errors++; break;
        case STATUS_ERR_OVERFLOW:
        default: break;
        }
        restart(dec);
        return result == STATUS_OK;
    }
    if (dec->raw_len < 0xFFFFFFFFu) {
        dec->raw_len++;
    }
    if (dec->overflow) {
        return 0;
    }
    if (cobs_unstuff_byte(byte, dec->buf, CMD_FRAME_MAX_DECODED_LEN, &dec->len, &dec->block_left,
                          &dec->zero_pending)) {
        dec->overflow = 1;
        dec->stats.overflows++;
    }
    return 0;
}
