/*
 * Reference code for the controller's side of the vlp-agent command link (spec: docs/wire-format.md,
 * "Commands"): encoders for the command frames the controller sends, and a decoder for the goal-status
 * frames the agent sends back on the same line as its pose frames.
 *
 *     wire = COBS(payload || CRC16-CCITT-FALSE(payload), little-endian) || 0x00
 *
 * C99, no dynamic allocation, no stdio, no floating point, independent of the host's byte order. Link it
 * with pose_frame.c (it shares pose_crc16_ccitt_false). The goal-status decoder takes one byte at a time and
 * skips the pose frames interleaved with the statuses (counted in `pose_frames`, not as errors), so a
 * controller feeds every received byte to both decoders. The Python codec (firmware_protocol/
 * command_frame.py) makes the same decisions; tests/unit/test_c_commands.py holds the two together.
 */
#ifndef VLP_COMMAND_FRAME_H
#define VLP_COMMAND_FRAME_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define CMD_FRAME_VERSION 0x10u         /* major << 4 | minor: 1.0 */
#define CMD_FRAME_MAX_PAYLOAD_LEN 64u   /* the longest a later v1.x may send */
#define CMD_FRAME_MAX_DECODED_LEN 66u   /* payload + CRC */
#define CMD_FRAME_MAX_WIRE_LEN 28u      /* the longest command this code writes (follow, v1.2) on the wire, 0x00
                                         * included */
#define CMD_FRAME_VERSION_FOLLOW 0x12u  /* follow frames are sent as 1.2 */

/* Type bytes (payload byte 0). */
#define CMD_TYPE_VELOCITY 0x21u
#define CMD_TYPE_GOAL 0x22u
#define CMD_TYPE_CANCEL 0x23u
#define CMD_TYPE_STOP 0x24u
#define CMD_TYPE_RESUME 0x25u
#define CMD_TYPE_FOLLOW 0x28u /* since v1.2 */
#define CMD_TYPE_GOAL_STATUS 0xA1u

#define CMD_NO_GOAL 0xFFFFu           /* cancel: whatever goal is active; status: no goal */
#define CMD_NO_SEQUENCE 0xFFFFu       /* status: sent by the agent on its own */
#define CMD_REMAINING_UNKNOWN 0xFFFFu /* status: remaining distance unknown */
#define CMD_GOAL_OPTION_YAW 0x01u     /* the goal's yaw is wanted */
#define CMD_GOAL_OPTION_ALLOW_UNKNOWN 0x02u
#define CMD_FOLLOW_START 0u             /* follow action: start following */
#define CMD_FOLLOW_STOP 1u              /* follow action: stop following */
#define CMD_FOLLOW_TAG_MAX_LEN 16u      /* bytes of a tag's EPC in a follow frame */

/* Goal states and reasons, as GoalState / GoalReason in the Python codec. */
enum {
    GOAL_ACCEPTED = 0, GOAL_REJECTED = 1, GOAL_ACTIVE = 2, GOAL_REACHED = 3, GOAL_FAILED = 4,
    GOAL_CANCELLED = 5
};
enum {
    REASON_NONE = 0, REASON_BAD_FRAME = 1, REASON_UNKNOWN_TYPE = 2, REASON_BAD_VERSION = 3,
    REASON_BAD_VALUE = 4, REASON_CLAMPED = 5, REASON_OUTSIDE_MAP = 6, REASON_IN_OBSTACLE = 7,
    REASON_UNREACHABLE = 8, REASON_BLOCKED = 9, REASON_TIMEOUT = 10, REASON_STOPPED = 11,
    REASON_SUPERSEDED = 12, REASON_NOT_LOCALIZED = 13, REASON_UNKNOWN_GOAL = 14, REASON_DEAD_MAN = 15,
    REASON_BUSY = 16,
    /* v1.1 (missions) */
    REASON_UNKNOWN_PLACE = 17, REASON_NO_FREE_SPACE = 18, REASON_START_BLOCKED = 19, REASON_EXPLORED = 20,
    /* v1.2 (following) */
    REASON_FOLLOW_UNAVAILABLE = 21, REASON_NO_TAG_READER = 22, REASON_FOLLOWING = 23, REASON_SEARCHING = 24,
    REASON_PERSON_LOST = 25, REASON_TAG_ABSENT = 26, REASON_NO_CAMERA_FRAMES = 27
};
#define REASON_LAST REASON_NO_CAMERA_FRAMES /* a later reason reads as REASON_NONE */

typedef struct {
    uint16_t sequence;
    uint16_t goal_id;
    uint8_t options;        /* CMD_GOAL_OPTION_* */
    int32_t x;              /* 0.1 mm, map frame */
    int32_t y;              /* 0.1 mm */
    int16_t yaw;            /* 2*pi/65536 rad; used only with CMD_GOAL_OPTION_YAW */
    uint16_t tolerance_xy;  /* mm, 0 = the agent's default */
    uint16_t tolerance_yaw; /* 1e-4 rad, 0 = the agent's default */
} cmd_goal_t;

typedef struct {
    uint8_t version;
    uint16_t sequence;         /* the agent's status counter */
    uint16_t command_sequence; /* the command answered, CMD_NO_SEQUENCE if none */
    uint16_t goal_id;          /* CMD_NO_GOAL if none */
    uint8_t state;             /* GOAL_* */
    uint8_t reason;            /* REASON_* (an unknown reason from a later version reads as REASON_NONE) */
    uint16_t remaining;        /* cm, CMD_REMAINING_UNKNOWN if unknown */
} goal_status_t;

/* Each encoder writes the whole frame, 0x00 included, into out (at least CMD_FRAME_MAX_WIRE_LEN bytes)
 * and returns its length. */
size_t cmd_encode_velocity(uint8_t *out, uint16_t sequence, int16_t v_mm_s, int16_t omega_mrad_s,
                           uint16_t timeout_ms);
size_t cmd_encode_goal(uint8_t *out, const cmd_goal_t *goal);
size_t cmd_encode_cancel(uint8_t *out, uint16_t sequence, uint16_t goal_id);
size_t cmd_encode_stop(uint8_t *out, uint16_t sequence);
size_t cmd_encode_resume(uint8_t *out, uint16_t sequence);
/* Follow (v1.2): CMD_FOLLOW_START the person wearing the tag (tag_len bytes of its EPC, most significant
 * first, at most CMD_FOLLOW_TAG_MAX_LEN; 0 and tag NULL: the agent's configured user tag), or
 * CMD_FOLLOW_STOP (tag_len 0). Returns 0, writing nothing, for an action or tag the agent would refuse. */
size_t cmd_encode_follow(uint8_t *out, uint16_t sequence, uint16_t follow_id, uint8_t action,
                         const uint8_t *tag, size_t tag_len);

typedef enum {
    STATUS_OK = 0,
    STATUS_ERR_COBS = 1,
    STATUS_ERR_LENGTH = 2,
    STATUS_ERR_CRC = 3,
    STATUS_ERR_TYPE = 4,    /* neither a goal status nor a pose frame */
    STATUS_ERR_VERSION = 5,
    STATUS_ERR_VALUE = 6,   /* an unknown goal state */
    STATUS_ERR_OVERFLOW = 7,
    STATUS_POSE = 8         /* a pose frame: not an error, leave it to the pose decoder */
} status_result_t;

typedef struct {
    uint32_t frames;
    uint32_t pose_frames;
    uint32_t cobs_errors;
    uint32_t length_errors;
    uint32_t crc_errors;
    uint32_t type_errors;
    uint32_t version_errors;
    uint32_t value_errors;
    uint32_t overflows;
} status_decoder_stats_t;

typedef struct {
    uint8_t buf[CMD_FRAME_MAX_DECODED_LEN];
    uint8_t len;
    uint8_t block_left;
    uint8_t zero_pending;
    uint8_t overflow;
    uint32_t raw_len;
    status_decoder_stats_t stats;
} status_decoder_t;

/* Check and decode one un-stuffed frame (payload followed by its CRC). Writes *out only on STATUS_OK. */
status_result_t goal_status_parse(const uint8_t *decoded, size_t len, goal_status_t *out);

void status_decoder_init(status_decoder_t *dec);

/* Feed one byte. Returns 1 and fills *out when this byte (a 0x00) completes a valid goal status, else 0. */
int status_decoder_feed(status_decoder_t *dec, uint8_t byte, goal_status_t *out);

#ifdef __cplusplus
}
#endif

#endif /* VLP_COMMAND_FRAME_H */
