/*
 * Reference decoder for the vlp-agent pose frame (spec: docs/wire-format.md).
 *
 *     wire = COBS(payload || CRC16-CCITT-FALSE(payload), little-endian) || 0x00
 *
 * Meant to be copied into controller firmware: C99, no dynamic allocation, no stdio, no floating point,
 * independent of the host's byte order and alignment. Feed it one received byte at a time (from a UART
 * interrupt or a DMA ring); it un-stuffs COBS on the fly into a 66-byte buffer and hands back a frame when
 * a 0x00 completes a valid one. Every rejected candidate is counted by cause and the decoder resyncs at
 * the next 0x00, so a corrupted frame never costs the one after it.
 *
 * The Python decoder (firmware_protocol/pose_frame.py) makes exactly the same decisions; the tests in
 * tests/unit/test_c_decoder.py hold the two together.
 */
#ifndef VLP_POSE_FRAME_H
#define VLP_POSE_FRAME_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* Version byte: major << 4 | minor. Decoders reject other majors and accept any minor of theirs. */
#define POSE_FRAME_VERSION_MAJOR 1u
#define POSE_FRAME_VERSION_MINOR 0u
#define POSE_FRAME_VERSION ((POSE_FRAME_VERSION_MAJOR << 4) | POSE_FRAME_VERSION_MINOR)

#define POSE_FRAME_PAYLOAD_LEN 30u     /* a v1.0 payload */
#define POSE_FRAME_MAX_PAYLOAD_LEN 64u /* the longest a later v1.x may send */
#define POSE_FRAME_CRC_LEN 2u
#define POSE_FRAME_MAX_DECODED_LEN (POSE_FRAME_MAX_PAYLOAD_LEN + POSE_FRAME_CRC_LEN) /* 66 */
#define POSE_FRAME_WIRE_LEN 34u        /* every v1.0 frame on the wire, delimiter included */

/* Units of the integer fields. */
#define POSE_FRAME_POSITION_PER_M 10000     /* x, y, sigma_xy: 0.1 mm */
#define POSE_FRAME_SIGMA_YAW_PER_RAD 10000  /* sigma_yaw: 1e-4 rad */
#define POSE_FRAME_YAW_STEPS_PER_TURN 65536 /* yaw: binary angle, 2*pi/65536 rad, -32768 = -pi */
#define POSE_FRAME_SIGMA_UNKNOWN 0xFFFFu    /* sigma_xy / sigma_yaw: unknown or out of range */

/* The status word (flags). Bits not named are reserved: ignore them. */
#define POSE_FLAG_VLP 0x0001u
#define POSE_FLAG_SLAM 0x0002u
#define POSE_FLAG_ODOMETRY 0x0004u
#define POSE_FLAG_IMU 0x0008u
#define POSE_FLAG_DEGRADED 0x0100u
#define POSE_FLAG_LASER_LOST 0x0200u
#define POSE_FLAG_CAMERA_STALLED 0x0400u
#define POSE_FLAG_SERVO_FAULT 0x0800u

typedef struct {
    uint8_t version;          /* as received: 0x10 for v1.0 */
    uint8_t reset_counter;    /* +1 whenever the pose jumps */
    uint16_t flags;           /* POSE_FLAG_* */
    uint32_t sequence;        /* +1 per frame, wrapping */
    uint64_t t_us;            /* capture time, microseconds, the agent's monotonic clock */
    int32_t x;                /* 0.1 mm */
    int32_t y;                /* 0.1 mm */
    int16_t yaw;              /* 2*pi/65536 rad, counter-clockwise */
    uint16_t sigma_xy;        /* 0.1 mm, POSE_FRAME_SIGMA_UNKNOWN = unknown */
    uint16_t sigma_yaw;       /* 1e-4 rad, POSE_FRAME_SIGMA_UNKNOWN = unknown */
} pose_frame_t;

typedef enum {
    POSE_OK = 0,
    POSE_ERR_COBS = 1,     /* a 0x00 arrived in the middle of a COBS block (frame cut short) */
    POSE_ERR_LENGTH = 2,   /* too short or too long for its version */
    POSE_ERR_CRC = 3,      /* CRC mismatch */
    POSE_ERR_VERSION = 4,  /* unknown major version */
    POSE_ERR_OVERFLOW = 5  /* more than 67 bytes without a 0x00: counted as the 68th arrives */
} pose_status_t;

typedef struct {
    uint32_t frames;          /* valid frames returned */
    uint32_t crc_errors;
    uint32_t length_errors;
    uint32_t cobs_errors;
    uint32_t version_errors;
    uint32_t overflows;       /* runs of more than 67 bytes without a 0x00, counted as the 68th arrives */
    uint32_t discarded_bytes; /* bytes of rejected candidates, their 0x00 included */
} pose_decoder_stats_t;

typedef struct {
    uint8_t buf[POSE_FRAME_MAX_DECODED_LEN]; /* un-stuffed bytes of the current candidate */
    uint8_t len;                             /* bytes in buf */
    uint8_t block_left;                      /* data bytes still due in the current COBS block */
    uint8_t zero_pending;                    /* the current block ends in an implied 0x00 */
    uint8_t overflow;                        /* skipping to the next 0x00 */
    uint32_t raw_len;                        /* bytes received since the last 0x00 */
    pose_status_t last_error;                /* cause of the last rejection (POSE_OK if none yet) */
    pose_decoder_stats_t stats;
} pose_decoder_t;

/* CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, no reflection, no final XOR. "123456789" -> 0x29B1. */
uint16_t pose_crc16_ccitt_false(const uint8_t *data, size_t len);

/* Check and decode one un-stuffed frame (payload followed by its CRC). Writes *out only on POSE_OK. */
pose_status_t pose_frame_parse(const uint8_t *decoded, size_t len, pose_frame_t *out);

/* One byte of a COBS-stuffed candidate (any byte but the 0x00 delimiter) un-stuffed into buf (cap bytes);
 * *len, *block_left and *zero_pending carry the state between bytes and start at 0. Shared by the pose
 * decoder and the goal-status decoder (command_frame.c). Returns 1 when buf is full (the candidate
 * overflows: skip to the next 0x00), else 0. */
int cobs_unstuff_byte(uint8_t byte, uint8_t *buf, uint8_t cap, uint8_t *len, uint8_t *block_left,
                      uint8_t *zero_pending);

/* Start (or restart) a decoder; counters are zeroed. */
void pose_decoder_init(pose_decoder_t *dec);

/* Forget a partial frame (e.g. after a UART error) without counting it; counters are kept. */
void pose_decoder_reset(pose_decoder_t *dec);

/* Feed one byte. Returns 1 and fills *out when this byte (a 0x00) completes a valid frame, else 0. */
int pose_decoder_feed(pose_decoder_t *dec, uint8_t byte, pose_frame_t *out);

#ifdef __cplusplus
}
#endif

#endif /* VLP_POSE_FRAME_H */
