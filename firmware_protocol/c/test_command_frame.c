/*
 * Test program for the reference command encoders and goal-status decoder.
 *
 *   test_command_frame --encode       read commands from stdin, one per line, print each frame in hex:
 *                                       v SEQ V_MM_S OMEGA_MRAD_S TIMEOUT_MS
 *                                       g SEQ GOAL_ID OPTIONS X Y YAW TOL_XY TOL_YAW
 *                                       c SEQ GOAL_ID      s SEQ      r SEQ
 *                                       f SEQ FOLLOW_ID ACTION TAGHEX  (TAGHEX "-": no tag)
 *   test_command_frame FILE           decode the goal statuses in a byte stream from FILE ("-" = stdin):
 *                                     one CSV line per status on stdout, the decoder's counters on stderr
 *
 * CSV columns: seq,command_seq,goal_id,state,reason,remaining,version.
 */
#include <inttypes.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "command_frame.h"

static void print_hex(const uint8_t *p, size_t n)
{
    size_t i;
    for (i = 0; i < n; i++) {
        printf(i ? " %02x" : "%02x", p[i]);
    }
    printf("\n");
}

/* "SEQ FOLLOW_ID ACTION TAGHEX": the follow frame into out, its length into *n; 0 if the line is bad. */
static int follow_line(const char *text, uint8_t *out, size_t *n)
{
    long seq, id, action;
    char hex[2 * CMD_FOLLOW_TAG_MAX_LEN + 8];
    uint8_t tag[CMD_FOLLOW_TAG_MAX_LEN];
    size_t len = 0u;
    unsigned int byte;

    if (sscanf(text, "%ld %ld %ld %34s", &seq, &id, &action, hex) != 4) {
        return 0;
    }
    if (strcmp(hex, "-") != 0) {
        size_t digits = strlen(hex);
        if (digits % 2u != 0u || digits / 2u > CMD_FOLLOW_TAG_MAX_LEN) {
            return 0;
        }
        for (len = 0; len < digits / 2u; len++) {
            if (sscanf(hex + 2u * len, "%2x", &byte) != 1) {
                return 0;
            }
            tag[len] = (uint8_t)byte;
        }
    }
    *n = cmd_encode_follow(out, (uint16_t)seq, (uint16_t)id, (uint8_t)action, len ? tag : NULL, len);
    return *n != 0u;
}

static int encode_lines(void)
{
    char line[256];
    uint8_t out[CMD_FRAME_MAX_WIRE_LEN];
    long a[8];
    size_t n;

    while (fgets(line, sizeof line, stdin) != NULL) {
        char kind = line[0];
        int got = sscanf(line + 1, "%ld %ld %ld %ld %ld %ld %ld %ld", &a[0], &a[1], &a[2], &a[3], &a[4], &a[5],
                         &a[6], &a[7]);
        if (kind == 'v' && got == 4) {
            n = cmd_encode_velocity(out, (uint16_t)a[0], (int16_t)a[1], (int16_t)a[2], (uint16_t)a[3]);
        } else if (kind == 'g' && got == 8) {
            cmd_goal_t g;
            g.sequence = (uint16_t)a[0];
            g.goal_id = (uint16_t)a[1];
            g.options = (uint8_t)a[2];
            g.x = (int32_t)a[3];
            g.y = (int32_t)a[4];
            g.yaw = (int16_t)a[5];
            g.tolerance_xy = (uint16_t)a[6];
            g.tolerance_yaw = (uint16_t)a[7];
            n = cmd_encode_goal(out, &g);
        } else if (kind == 'c' && got == 2) {
            n = cmd_encode_cancel(out, (uint16_t)a[0], (uint16_t)a[1]);
        } else if (kind == 's' && got == 1) {
            n = cmd_encode_stop(out, (uint16_t)a[0]);
        } else if (kind == 'r' && got == 1) {
            n = cmd_encode_resume(out, (uint16_t)a[0]);
        } else if (kind == 'f' && follow_line(line + 1, out, &n)) {
            /* n set */
        } else {
            fprintf(stderr, "bad line: %s", line);
            return 2;
        }
        print_hex(out, n);
    }
    return 0;
}

static int decode_stream(const char *path)
{
    FILE *f = strcmp(path, "-") == 0 ? stdin : fopen(path, "rb");
    status_decoder_t dec;
    goal_status_t s;
    int c;

    if (f == NULL) {
        perror(path);
        return 2;
    }
    status_decoder_init(&dec);
    printf("seq,command_seq,goal_id,state,reason,remaining,version\n");
    while ((c = fgetc(f)) != EOF) {
        if (status_decoder_feed(&dec, (uint8_t)c, &s)) {
            printf("%u,%u,%u,%u,%u,%u,%u\n", s.sequence, s.command_sequence, s.goal_id, s.state, s.reason,
                   s.remaining, s.version);
        }
    }
    fprintf(stderr,
            "frames=%" PRIu32 " pose_frames=%" PRIu32 " cobs_errors=%" PRIu32 " length_errors=%" PRIu32
            " crc_errors=%" PRIu32 " type_errors=%" PRIu32 " version_errors=%" PRIu32 " value_errors=%" PRIu32
            " overflows=%" PRIu32 "\n",
            dec.stats.frames, dec.stats.pose_frames, dec.stats.cobs_errors, dec.stats.length_errors,
            dec.stats.crc_errors, dec.stats.type_errors, dec.stats.version_errors, dec.stats.value_errors,
            dec.stats.overflows);
    if (f != stdin) {
        fclose(f);
    }
    return 0;
}

int main(int argc, char **argv)
{
    if (argc == 2 && strcmp(argv[1], "--encode") == 0) {
        return encode_lines();
    }
    if (argc == 2) {
        return decode_stream(argv[1]);
    }
    fprintf(stderr, "usage: %s --encode | FILE\n", argv[0]);
    return 2;
}
