/*
 * fbg_board_host: the firmware's sampling loop (scheduler + board + AHT10 state machine from
 * firmware/core) run against a simulated board clock and a simulated AHT10 on a simulated I2C bus.
 *
 * Event-driven: the clock jumps to the next event (an ADC read time, possibly made late on
 * purpose with --late K:US, or an AHT10 poll time). At equal times the AHT10 is polled first.
 * Reading the four channels takes --adc-read-us (default 40 us, a simulation parameter, not a
 * measured ESP32 figure): a read that catches up starts when the previous one is done, so t_us
 * increases strictly.
 *
 * Options: --rate-mhz R (sample rate in mHz, default 100000 = 100 Hz), --samples N or
 * --duration-us US, --output frames|times, --every N, --late K:US (repeatable), --adc-read-us US, --aux
 * (a fifth synthetic channel, (29 k + 7) mod 4096 for read k, sent in protocol-version-2 frames),
 * --aht aht10|aht20|absent, --aht-fault nack|busy|badcrc|range|uncal|ones:START_US:END_US
 * (repeatable), --temp-start-cc CC, --temp-slope-cc-per-s CC, --aht-period-us US, --aht-log,
 * --link-connect-us US, --link-down-us START_US:END_US (repeatable).
 *
 * Link model (the ESP32 writer task, firmware/esp32/fbg_board/fbg_board.ino): a frame whose sample was
 * taken before --link-connect-us, or at START_US <= t_us < END_US of a --link-down-us window, is
 * discarded as the SPP writer discards frames while no client is connected (sampling and seq go on);
 * every other frame is sent through fbg_link_on_send, which puts BOOT on the first one sent after
 * power-up. Without these options every frame is sent (USB serial).
 *
 * Output (stdout): --output frames (default) writes the frames sent (protocol v1, or v2 with --aux);
 * --output times writes "k seq t_us status" (status as sent) for every --every-th sample and for the
 * last one, if the link sent it; the END line counts every sample taken, sent or not. --aht-log writes one line per
 * completed AHT10 measurement, or change of the temperature state the frames carry, on stderr:
 * "AHT <t_us> <reason|state> <raw_t> <temp_cc> <status_bits>".
 * Usage errors: one line on stderr, exit code 2.
 */
#include <errno.h>
#include <inttypes.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "aht10_sim_device.h"
#include "fbg_aht10.h"
#include "fbg_board.h"
#include "fbg_frame.h"
#include "fbg_scheduler.h"

#define MAX_LATE 64
#define MAX_LINK_DOWN 64

static const char *const REASON_NAMES[FBG_AHT10_REASONS] = {"ok", "none_yet", "absent", "nack", "stuck",
                                                            "bad_crc", "uncalibrated", "bus_stuck", "out_of_range"};
static const char *const FAULT_NAMES[SIM_FAULT_KINDS] = {"nack", "busy", "badcrc", "range", "uncal", "ones"};

static int usage(const char *msg, const char *arg)
{
    fprintf(stderr, "fbg_board_host: error: %s%s%s (see the comment at the top of firmware/host/fbg_board_host.c)\n", msg,
            arg ? ": " : "", arg ? arg : "");
    return 2;
}

static int parse_u64(const char *s, uint64_t *out)
{
    char *end;
    unsigned long long v;
    if (s == NULL || *s == '\0' || *s == '-') {
        return -1;
    }
    errno = 0;
    v = strtoull(s, &end, 10);
    if (errno != 0 || *end != '\0') {
        return -1;
    }
    *out = (uint64_t)v;
    return 0;
}

static int parse_i64(const char *s, int64_t *out)
{
    char *end;
    long long v;
    if (s == NULL || *s == '\0') {
        return -1;
    }
    errno = 0;
    v = strtoll(s, &end, 10);
    if (errno != 0 || *end != '\0') {
        return -1;
    }
    *out = (int64_t)v;
    return 0;
}

/* "A:B" -> two non-negative integers; -1 if malformed. */
static int parse_u64_pair(const char *v, uint64_t *a, uint64_t *b)
{
    char buf[64];
    char *colon;
    if (strlen(v) >= sizeof buf) {
        return -1;
    }
    strcpy(buf, v);
    colon = strchr(buf, ':');
    if (colon == NULL) {
        return -1;
    }
    *colon = '\0';
    return parse_u64(buf, a) != 0 || parse_u64(colon + 1, b) != 0 ? -1 : 0;
}

/* The aux channel of read k (--aux): a ramp the test can predict (docs/protocol.md, version 2). */
static uint16_t synthetic_aux(uint64_t k)
{
    return (uint16_t)((k * 29u + 7u) % 4096u);
}

/* Synthetic ADC counts for sample k: deterministic, covering 0..4095. */
static void synthetic_adc(uint64_t k, uint16_t adc[4])
{
    adc[0] = (uint16_t)(800u + (k % 100u));
    adc[1] = (uint16_t)((k * 7u) % 4096u);
    adc[2] = (uint16_t)((k * 13u + 1000u) % 4096u);
    adc[3] = (uint16_t)(4095u - (k % 4096u));
}

int main(int argc, char **argv)
{
    uint64_t rate_mhz = 100000u, samples = 0, duration_us = 0, every = 1;
    int output_times = 0, aht_log = 0, with_aux = 0, i;
    uint64_t late_k[MAX_LATE], late_us[MAX_LATE];
    int n_late = 0;
    uint64_t link_connect_us = 0, down_from[MAX_LINK_DOWN], down_to[MAX_LINK_DOWN];
    int n_down = 0;
    fbg_link link;
    int absent_logged = 0;
    uint8_t bits, last_bits = 0;
    int16_t cc, last_cc = 0;
    static uint64_t now_us = 0;
    aht10_sim_device dev;
    fbg_aht10_config acfg = fbg_aht10_default_config();
    fbg_aht10 aht;
    fbg_board board;
    fbg_scheduler sched;
    fbg_i2c_bus bus;
    uint64_t k = 0, aht_wake, last_counts_total = 0;
    uint64_t adc_read_us = 40u, adc_free_us = 0;
    static char outbuf[1 << 16];

    aht10_sim_init(&dev, &now_us);
    for (i = 1; i < argc; i++) {
        const char *a = argv[i];
        const char *v = (i + 1 < argc) ? argv[i + 1] : NULL;
        if (strcmp(a, "--aht-log") == 0) {
            aht_log = 1;
            continue;
        }
        if (strcmp(a, "--aux") == 0) { /* a fifth channel (reference transducer): protocol-version-2 frames */
            with_aux = 1;
            continue;
        }
        if (v == NULL) {
            return usage("option needs a value", a);
        }
        i++;
        if (strcmp(a, "--rate-mhz") == 0) {
            if (parse_u64(v, &rate_mhz) != 0 || rate_mhz == 0 || rate_mhz > 1000000000u) {
                return usage("--rate-mhz must be an integer in 1..1000000000 (millihertz)", v);
            }
        } else if (strcmp(a, "--samples") == 0) {
            if (parse_u64(v, &samples) != 0) {
                return usage("--samples must be a non-negative integer", v);
            }
        } else if (strcmp(a, "--duration-us") == 0) {
            if (parse_u64(v, &duration_us) != 0) {
                return usage("--duration-us must be a non-negative integer", v);
            }
        } else if (strcmp(a, "--every") == 0) {
            if (parse_u64(v, &every) != 0 || every == 0) {
                return usage("--every must be a positive integer", v);
            }
        } else if (strcmp(a, "--output") == 0) {
            if (strcmp(v, "frames") == 0) {
                output_times = 0;
            } else if (strcmp(v, "times") == 0) {
                output_times = 1;
            } else {
                return usage("--output must be frames or times", v);
            }
        } else if (strcmp(a, "--adc-read-us") == 0) {
            if (parse_u64(v, &adc_read_us) != 0 || adc_read_us == 0 || adc_read_us > 1000000u) {
                return usage("--adc-read-us must be an integer in 1..1000000", v);
            }
        } else if (strcmp(a, "--late") == 0) { /* K:US: read k is taken US microseconds after its time */
            if (n_late >= MAX_LATE || parse_u64_pair(v, &late_k[n_late], &late_us[n_late]) != 0) {
                return usage("--late needs K:US with non-negative integers (at most 64)", v);
            }
            n_late++;
        } else if (strcmp(a, "--link-connect-us") == 0) { /* no client before this board time */
            if (parse_u64(v, &link_connect_us) != 0) {
                return usage("--link-connect-us must be a non-negative integer (board time, us)", v);
            }
        } else if (strcmp(a, "--link-down-us") == 0) { /* START_US:END_US: no client while START <= t_us < END */
            if (n_down >= MAX_LINK_DOWN || parse_u64_pair(v, &down_from[n_down], &down_to[n_down]) != 0 ||
                down_to[n_down] < down_from[n_down]) {
                return usage("--link-down-us needs START_US:END_US with START_US <= END_US (at most 64)", v);
            }
            n_down++;
        } else if (strcmp(a, "--aht") == 0) {
            if (strcmp(v, "aht10") == 0) {
                dev.send_crc = 0;
                acfg.check_crc = 0;
            } else if (strcmp(v, "aht20") == 0) {
                dev.send_crc = 1;
                acfg.check_crc = 1;
            } else if (strcmp(v, "absent") == 0) {
                dev.absent = 1;
            } else {
                return usage("--aht must be aht10, aht20 or absent", v);
            }
        } else if (strcmp(a, "--aht-fault") == 0) { /* KIND:START_US:END_US */
            char buf[96];
            char *c1, *c2;
            int kind;
            sim_fault_window *w;
            if (dev.n_windows >= SIM_MAX_WINDOWS || strlen(v) >= sizeof buf) {
                return usage("too many --aht-fault options or value too long", v);
            }
            strcpy(buf, v);
            c1 = strchr(buf, ':');
            c2 = c1 ? strchr(c1 + 1, ':') : NULL;
            if (c2 == NULL) {
                return usage("--aht-fault needs KIND:START_US:END_US", v);
            }
            *c1 = '\0';
            *c2 = '\0';
            for (kind = 0; kind < SIM_FAULT_KINDS && strcmp(buf, FAULT_NAMES[kind]) != 0; kind++) {
            }
            if (kind == SIM_FAULT_KINDS) {
                return usage("--aht-fault KIND must be nack, busy, badcrc, range, uncal or ones", buf);
            }
            w = &dev.windows[dev.n_windows];
            w->kind = kind;
            if (parse_u64(c1 + 1, &w->start_us) != 0 || parse_u64(c2 + 1, &w->end_us) != 0 || w->end_us < w->start_us) {
                return usage("--aht-fault START_US and END_US must be integers with START_US <= END_US", v);
            }
            dev.n_windows++;
        } else if (strcmp(a, "--temp-start-cc") == 0) {
            if (parse_i64(v, &dev.temp_start_cc) != 0) {
                return usage("--temp-start-cc must be an integer (0.01 degC)", v);
            }
        } else if (strcmp(a, "--temp-slope-cc-per-s") == 0) {
            if (parse_i64(v, &dev.temp_slope_cc_per_s) != 0) {
                return usage("--temp-slope-cc-per-s must be an integer (0.01 degC/s)", v);
            }
        } else if (strcmp(a, "--aht-period-us") == 0) {
            uint64_t p;
            if (parse_u64(v, &p) != 0 || p < 100000u || p > 60000000u) {
                return usage("--aht-period-us must be in 100000..60000000", v);
            }
            acfg.period_us = (uint32_t)p;
        } else {
            return usage("unknown option", a);
        }
    }
    if ((samples == 0) == (duration_us == 0)) {
        return usage("give exactly one of --samples N or --duration-us US (non-zero)", NULL);
    }

    setvbuf(stdout, outbuf, _IOFBF, sizeof outbuf);
    bus.write = aht10_sim_write;
    bus.read = aht10_sim_read;
    bus.ctx = &dev;
    fbg_board_init(&board);
    fbg_link_init(&link);
    fbg_aht10_init(&aht, &acfg, 0);
    (void)fbg_sched_init(&sched, (uint32_t)rate_mhz, 0);
    aht_wake = aht.wake_us;

    for (;;) {
        uint64_t read_at = fbg_sched_next_us(&sched);
        uint64_t extra = 0;
        int j;
        for (j = 0; j < n_late; j++) {
            if (late_k[j] == sched.index) {
                extra += late_us[j];
            }
        }
        read_at += extra;
        if (read_at < adc_free_us) { /* catching up: the next read starts when the previous one is done */
            read_at = adc_free_us;
        }
        if (samples != 0 ? k >= samples : read_at >= duration_us) {
            break;
        }
        if (aht_wake <= read_at) { /* I2C task runs first at equal times */
            uint64_t total = 0;
            int r;
            now_us = aht_wake;
            aht_wake = fbg_aht10_poll(&aht, &bus, now_us);
            for (r = 0; r < FBG_AHT10_REASONS; r++) {
                total += aht.counts[r];
            }
            bits = fbg_aht10_status_bits(&aht);
            cc = fbg_aht10_temp_cc(&aht);
            if (aht_log && (total != last_counts_total || bits != last_bits || cc != last_cc ||
                            (aht.state == FBG_AHT10_S_ABSENT && !absent_logged))) {
                fprintf(stderr, "AHT %" PRIu64 " %s %" PRIu32 " %d %u\n", now_us,
                        total != last_counts_total || aht.state == FBG_AHT10_S_ABSENT ? REASON_NAMES[aht.last_reason]
                                                                                      : "state",
                        aht.last_raw, (int)cc, (unsigned)bits);
                absent_logged = aht.state == FBG_AHT10_S_ABSENT;
            }
            last_bits = bits;
            last_cc = cc;
            last_counts_total = total;
            continue;
        }
        {
            uint16_t adc[4];
            uint16_t aux;
            fbg_sample s;
            uint32_t skipped = 0;
            int late, sent = 1;
            uint8_t frame[FBG_FRAME_SIZE_V2];
            size_t size;
            now_us = read_at;
            adc_free_us = now_us + adc_read_us;
            synthetic_adc(sched.index, adc);
            aux = synthetic_aux(sched.index); /* read fifth, after z (ESP32 one-shot conversions in sequence) */
            late = fbg_sched_take(&sched, now_us, &skipped);
            fbg_board_next_sample(&board, now_us, adc, fbg_aht10_temp_cc(&aht), fbg_aht10_status_bits(&aht), late, &s);
            fbg_board_skip(&board, skipped);
            size = with_aux ? fbg_frame_encode_v2(&s, aux, frame) : fbg_frame_encode_v1(&s, frame);
            /* the writer task: discard with no client, else send through the BOOT marker */
            if (now_us < link_connect_us) {
                sent = 0;
            }
            for (j = 0; j < n_down; j++) {
                if (down_from[j] <= now_us && now_us < down_to[j]) {
                    sent = 0;
                }
            }
            if (sent && fbg_link_on_send(&link, frame, size) < 0) {
                fprintf(stderr, "fbg_board_host: error: fbg_link_on_send refused an encoded frame\n");
                return 1;
            }
            s.status = frame[FBG_STATUS_OFFSET]; /* as sent */
            if (!sent) {
                /* discarded by the writer: nothing on the link */
            } else if (output_times) {
                if (k % every == 0) {
                    printf("%" PRIu64 " %u %" PRIu64 " %u\n", k, (unsigned)s.seq, s.t_us, (unsigned)s.status);
                }
            } else {
                if (fwrite(frame, 1, size, stdout) != size) {
                    fprintf(stderr, "fbg_board_host: error: cannot write to stdout\n");
                    return 1;
                }
            }
            k++;
            if (output_times && sent && ((samples != 0 && k == samples) ||
                                 (duration_us != 0 && fbg_sched_next_us(&sched) >= duration_us)) &&
                (k - 1) % every != 0) {
                printf("%" PRIu64 " %u %" PRIu64 " %u\n", k - 1, (unsigned)s.seq, s.t_us, (unsigned)s.status);
            }
        }
    }
    if (output_times) {
        printf("END samples=%" PRIu64 " skipped=%" PRIu64 "\n", k, sched.skipped);
    }
    return fflush(stdout) == 0 ? 0 : 1;
}
