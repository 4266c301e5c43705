/*
 * fbg_encode: host build of the firmware's frame encoder (firmware/core/fbg_frame.c).
 *
 * Reads one sample per line on stdin, eight or nine decimal fields separated by blanks:
 *     seq t_us ref x y z temp_cc status [aux]
 * (blank lines and lines starting with '#' are skipped) and writes one frame per sample to stdout:
 * 27-byte protocol v1, or 29-byte protocol v2 when the line has the aux counts (0..4095). A malformed line stops the program with a one-line error naming the line
 * and the field, and exit code 2; the frames of the lines before it have been written.
 */
#include <errno.h>
#include <inttypes.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fbg_frame.h"

#define LINE_MAX_LEN 512

static const char *const FIELD_NAMES[9] = {"seq", "t_us", "ref", "x", "y", "z", "temp_cc", "status", "aux"};

static int fail(unsigned long line, const char *what)
{
    fflush(stdout);
    fprintf(stderr, "fbg_encode: error: stdin line %lu: %s (expected: seq t_us ref x y z temp_cc status [aux], decimal)\n",
            line, what);
    return 2;
}

/* Parse one decimal integer field in [lo, hi] (hi as unsigned for t_us); 0 on success. */
static int parse_field(char **cursor, int is_signed, int64_t lo, uint64_t hi, uint64_t *u, int64_t *s)
{
    char *end;
    char *p = *cursor;
    while (*p == ' ' || *p == '\t') {
        p++;
    }
    if (*p == '\0' || *p == '\n' || *p == '\r') {
        return -1; /* missing */
    }
    errno = 0;
    if (is_signed) {
        long long v = strtoll(p, &end, 10);
        if (end == p || errno != 0 || v < lo || v > (long long)hi) {
            return -2;
        }
        *s = (int64_t)v;
    } else {
        unsigned long long v;
        if (*p == '-' || *p == '+') {
            return -2;
        }
        v = strtoull(p, &end, 10);
        if (end == p || errno != 0 || v > hi) {
            return -2;
        }
        *u = (uint64_t)v;
    }
    if (*end != '\0' && *end != ' ' && *end != '\t' && *end != '\n' && *end != '\r') {
        return -2;
    }
    *cursor = end;
    return 0;
}

int main(void)
{
    char line[LINE_MAX_LEN];
    char msg[160];
    unsigned long lineno = 0;
    static char outbuf[1 << 16];
    setvbuf(stdout, outbuf, _IOFBF, sizeof outbuf);
    while (fgets(line, sizeof line, stdin) != NULL) {
        char *p = line;
        uint64_t u[9] = {0};
        int has_aux = 0;
        int64_t sv = 0;
        fbg_sample s;
        uint8_t frame[FBG_FRAME_SIZE_V2];
        size_t size;
        int i;
        lineno++;
        if (strchr(line, '\n') == NULL && !feof(stdin)) {
            return fail(lineno, "line too long");
        }
        while (*p == ' ' || *p == '\t') {
            p++;
        }
        if (*p == '#' || *p == '\n' || *p == '\r' || *p == '\0') {
            continue;
        }
        for (i = 0; i < 8; i++) {
            static const uint64_t HI[8] = {65535u, UINT64_MAX, FBG_ADC_MAX, FBG_ADC_MAX, FBG_ADC_MAX, FBG_ADC_MAX,
                                           32767u, 255u};
            int rc = parse_field(&p, i == 6, i == 6 ? -32768 : 0, HI[i], &u[i], &sv);
            if (rc != 0) {
                if (rc == -1) {
                    snprintf(msg, sizeof msg, "field '%s' missing", FIELD_NAMES[i]);
                } else if (i == 6) {
                    snprintf(msg, sizeof msg, "field '%s' is not an integer in -32768..32767", FIELD_NAMES[i]);
                } else {
                    snprintf(msg, sizeof msg, "field '%s' is not an integer in 0..%" PRIu64, FIELD_NAMES[i], HI[i]);
                }
                return fail(lineno, msg);
            }
        }
        while (*p == ' ' || *p == '\t' || *p == '\r' || *p == '\n') {
            p++;
        }
        if (*p != '\0') { /* the optional aux field: a version-2 frame */
            int64_t unused = 0;
            if (parse_field(&p, 0, 0, FBG_ADC_MAX, &u[8], &unused) != 0) {
                snprintf(msg, sizeof msg, "field '%s' is not an integer in 0..%u", FIELD_NAMES[8], (unsigned)FBG_ADC_MAX);
                return fail(lineno, msg);
            }
            has_aux = 1;
            while (*p == ' ' || *p == '\t' || *p == '\r' || *p == '\n') {
                p++;
            }
            if (*p != '\0') {
                return fail(lineno, "more than 9 fields");
            }
        }
        s.seq = (uint16_t)u[0];
        s.t_us = u[1];
        s.ref = (uint16_t)u[2];
        s.x = (uint16_t)u[3];
        s.y = (uint16_t)u[4];
        s.z = (uint16_t)u[5];
        s.temp_cc = (int16_t)sv;
        s.status = (uint8_t)u[7];
        size = has_aux ? fbg_frame_encode_v2(&s, (uint16_t)u[8], frame) : fbg_frame_encode_v1(&s, frame);
        if (fwrite(frame, 1, size, stdout) != size) {
            fprintf(stderr, "fbg_encode: error: cannot write to stdout\n");
            return 1;
        }
    }
    if (ferror(stdin)) {
        fprintf(stderr, "fbg_encode: error: cannot read stdin\n");
        return 1;
    }
    return fflush(stdout) == 0 ? 0 : 1;
}
