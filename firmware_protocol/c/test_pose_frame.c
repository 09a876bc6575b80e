/*
 * Test program for the reference pose-frame decoder.
 *
 *   test_pose_frame --vectors       check the test vectors of docs/wire-format.md (exit 0 if all pass)
 *   test_pose_frame --list-vectors  print each vector's wire bytes in hex, one per line
 *   test_pose_frame FILE            decode a byte stream from FILE ("-" = stdin): one CSV line per frame
 *                                   on stdout, then the decoder's counters on stderr
 *
 * CSV columns: seq,t_us,x_m,y_m,yaw_rad,sigma_xy_m,sigma_yaw_rad,flags,reset_counter,version. Positions
 * and sigmas are printed exactly from their fixed-point values (4 decimals, "inf" for unknown); yaw is
 * the double yaw * (pi / 32768) printed with %.17g, so it reads back as the same double.
 */
#include <inttypes.h>
#include <stdio.h>
#include <string.h>

#include "pose_frame.h"

typedef struct {
    const char *name;
    uint8_t wire[POSE_FRAME_WIRE_LEN];
    pose_frame_t expect;
} vector_t;

/* Copied from docs/wire-format.md, "Test vectors"; tests/unit/test_c_decoder.py checks they agree. */
static const vector_t VECTORS[] = {
    {"1 at rest at the origin, nothing live yet",
     {0x02, 0x10, 0x01, 0x01, 0x01, 0x01, 0x01, 0x01, 0x01, 0x01, 0x01, 0x01, 0x01, 0x01, 0x01, 0x01, 0x01,
      0x01, 0x01, 0x01, 0x01, 0x01, 0x01, 0x01, 0x01, 0x01, 0x01, 0x01, 0x01, 0x01, 0x03, 0xb5, 0xbb, 0x00},
     {0x10, 0, 0x0000u, 0u, 0u, 0, 0, 0, 0u, 0u}},
    {"2 nominal: every source live",
     {0x04, 0x10, 0x03, 0x0f, 0x03, 0xd2, 0x04, 0x01, 0x06, 0x35, 0x1c, 0xdc, 0xdf, 0x02, 0x01, 0x01, 0x03,
      0xb8, 0x7a, 0x01, 0x08, 0x58, 0x9e, 0xff, 0xff, 0x1e, 0x3d, 0x15, 0x02, 0x57, 0x03, 0x27, 0x88, 0x00},
     {0x10, 3, 0x000Fu, 1234u, UINT64_C(12345678901), 31416, -25000, 15646, 21u, 87u}},
    {"3 laser lost, position error unknown, yaw at -pi",
     {0x09, 0x10, 0xff, 0x0d, 0x03, 0xff, 0xff, 0xff, 0xff, 0x05, 0x60, 0xd7, 0x1d, 0x14, 0x01, 0x01, 0x08,
      0xc0, 0x1d, 0xfe, 0xff, 0x55, 0xf8, 0x06, 0x01, 0x08, 0x80, 0xff, 0xff, 0xac, 0x0d, 0x81, 0x88, 0x00},
     {0x10, 255, 0x030Du, 0xFFFFFFFFu, UINT64_C(86400000000), -123456, 456789, -32767 - 1, 0xFFFFu, 3500u}},
    {"4 camera stalled and a servo fault",
     {0x05, 0x10, 0x01, 0x0a, 0x0d, 0x01, 0x02, 0x01, 0x04, 0x40, 0x42, 0x0f, 0x01, 0x01, 0x01, 0x01, 0x02,
      0x01, 0x01, 0x01, 0x0d, 0xff, 0xff, 0xff, 0xff, 0x3b, 0x7a, 0x88, 0x13, 0xff, 0xff, 0xd1, 0xe9, 0x00},
     {0x10, 1, 0x0D0Au, 65536u, UINT64_C(1000000), 1, -1, 31291, 5000u, 0xFFFFu}},
};

#define N_VECTORS (sizeof VECTORS / sizeof VECTORS[0])

static int same_frame(const pose_frame_t *a, const pose_frame_t *b)
{
    return a->version == b->version && a->reset_counter == b->reset_counter && a->flags == b->flags &&
           a->sequence == b->sequence && a->t_us == b->t_us && a->x == b->x && a->y == b->y &&
           a->yaw == b->yaw && a->sigma_xy == b->sigma_xy && a->sigma_yaw == b->sigma_yaw;
}

static int check_vectors(void)
{
    static const uint8_t check_input[] = "123456789";
    pose_decoder_t dec;
    pose_frame_t frame;
    size_t v, i;
    int failures = 0;

    if (pose_crc16_ccitt_false(check_input, 9) != 0x29B1u) {
        printf("FAIL crc check value %04X != 29B1\n", (unsigned)pose_crc16_ccitt_false(check_input, 9));
        failures++;
    }
    for (v = 0; v < N_VECTORS; v++) {
        int got = 0;
        pose_decoder_init(&dec);
        for (i = 0; i < POSE_FRAME_WIRE_LEN; i++) {
            if (pose_decoder_feed(&dec, VECTORS[v].wire[i], &frame)) {
                got += (i == POSE_FRAME_WIRE_LEN - 1u) ? 1 : 100;
            }
        }
        if (got != 1 || !same_frame(&frame, &VECTORS[v].expect)) {
            printf("FAIL vector %s\n", VECTORS[v].name);
            failures++;
            continue;
        }
        /* Any single flipped bit in the stuffed bytes must be rejected, and counted as one bad frame. */
        for (i = 0; i + 1u < POSE_FRAME_WIRE_LEN; i++) {
            unsigned bit;
            for (bit = 0; bit < 8u; bit++) {
                size_t k;
                uint32_t bad;
                pose_decoder_init(&dec);
                for (k = 0; k < POSE_FRAME_WIRE_LEN; k++) {
                    uint8_t b = VECTORS[v].wire[k];
                    if (k == i) {
                        b = (uint8_t)(b ^ (1u << bit));
                    }
                    got = pose_decoder_feed(&dec, b, &frame);
                }
                bad = dec.stats.crc_errors + dec.stats.length_errors + dec.stats.cobs_errors +
                      dec.stats.version_errors;
                /* A flip to 0x00 splits the frame in two candidates, both bad. */
                if (got || dec.stats.frames != 0u || bad < 1u || bad > 2u) {
                    printf("FAIL vector %s: bit %u of byte %lu flipped was not rejected\n", VECTORS[v].name,
                           bit, (unsigned long)i);
                    failures++;
                }
            }
        }
        printf("ok   vector %s\n", VECTORS[v].name);
    }
    return failures == 0 ? 0 : 1;
}

static void list_vectors(void)
{
    size_t v, i;
    for (v = 0; v < N_VECTORS; v++) {
        for (i = 0; i < POSE_FRAME_WIRE_LEN; i++) {
            printf(i ? " %02x" : "%02x", VECTORS[v].wire[i]);
        }
        printf("\n");
    }
}

/* value / 10000 with exactly 4 decimals, or "inf" when it is the unknown marker. */
static void print_fixed(int64_t value, int unknown)
{
    uint64_t magnitude;
    if (unknown) {
        fputs("inf", stdout);
        return;
    }
    magnitude = value < 0 ? (uint64_t)(-(value + 1)) + 1u : (uint64_t)value;
    printf("%s%" PRIu64 ".%04u", value < 0 ? "-" : "", magnitude / 10000u, (unsigned)(magnitude % 10000u));
}

static void print_frame(const pose_frame_t *f)
{
    printf("%" PRIu32 ",%" PRIu64 ",", f->sequence, f->t_us);
    print_fixed(f->x, 0);
    putchar(',');
    print_fixed(f->y, 0);
    printf(",%.17g,", (double)f->yaw * (3.141592653589793 / 32768.0));
    print_fixed(f->sigma_xy, f->sigma_xy == POSE_FRAME_SIGMA_UNKNOWN);
    putchar(',');
    print_fixed(f->sigma_yaw, f->sigma_yaw == POSE_FRAME_SIGMA_UNKNOWN);
    printf(",0x%04X,%u,0x%02X\n", (unsigned)f->flags, (unsigned)f->reset_counter, (unsigned)f->version);
}

static int decode_stream(const char *path)
{
    static uint8_t chunk[4096];
    pose_decoder_t dec;
    pose_frame_t frame;
    FILE *in = strcmp(path, "-") == 0 ? stdin : fopen(path, "rb");
    size_t n, i;

    if (in == NULL) {
        perror(path);
        return 2;
    }
    /* stdin is read as is: POSIX streams have no text mode (on Windows, pass a file path). */
    pose_decoder_init(&dec);
    puts("seq,t_us,x_m,y_m,yaw_rad,sigma_xy_m,sigma_yaw_rad,flags,reset_counter,version");
    while ((n = fread(chunk, 1, sizeof chunk, in)) > 0) {
        for (i = 0; i < n; i++) {
            if (pose_decoder_feed(&dec, chunk[i], &frame)) {
                print_frame(&frame);
            }
        }
    }
    if (ferror(in)) {
        perror(path);
        return 2;
    }
    if (in != stdin) {
        fclose(in);
    }
    fprintf(stderr,
            "frames=%" PRIu32 " crc_errors=%" PRIu32 " length_errors=%" PRIu32 " cobs_errors=%" PRIu32
            " version_errors=%" PRIu32 " overflows=%" PRIu32 " discarded_bytes=%" PRIu32 " pending=%" PRIu32
            "\n",
            dec.stats.frames, dec.stats.crc_errors, dec.stats.length_errors, dec.stats.cobs_errors,
            dec.stats.version_errors, dec.stats.overflows, dec.stats.discarded_bytes, dec.raw_len);
    return 0;
}

int main(int argc, char **argv)
{
    if (argc == 2 && strcmp(argv[1], "--vectors") == 0) {
        return check_vectors();
    }
    if (argc == 2 && strcmp(argv[1], "--list-vectors") == 0) {
        list_vectors();
        return 0;
    }
    if (argc == 2 && argv[1][0] != '\0' && (argv[1][0] != '-' || argv[1][1] == '\0')) {
        return decode_stream(argv[1]);
    }
    fprintf(stderr, "usage: %s --vectors | --list-vectors | FILE (- for stdin)\n", argv[0]);
    return 2;
}
