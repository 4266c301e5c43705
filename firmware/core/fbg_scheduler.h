/*
 * Drift-free sample scheduler: turns a sample-rate setting into ADC read times on the board clock.
 *
 * The rate is given in millihertz (100 Hz = 100000), so non-integer rates are exact. Read time k is
 * t0 + floor(k * 10^9 / rate_mhz) microseconds, computed incrementally with an integer quotient and
 * remainder (no floating point, no accumulated rounding): after any number of samples the schedule
 * is exactly where the formula puts it. Portable C99.
 */
#ifndef FBG_SCHEDULER_H
#define FBG_SCHEDULER_H

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define FBG_SCHED_MAX_CATCH_UP 4u /* late by more than this many periods: skip ahead instead of bursting */

typedef struct {
    uint64_t t0_us;       /**< board time of read 0 */
    uint32_t rate_mhz;    /**< sample rate, mHz */
    uint64_t whole_us;    /**< floor(10^9 / rate_mhz) */
    uint32_t rem;         /**< 10^9 mod rate_mhz */
    uint32_t acc;         /**< accumulated remainder, < rate_mhz */
    uint64_t index;       /**< index k of the next read */
    uint64_t next_us;     /**< scheduled board time of read k */
    uint64_t skipped;     /**< reads skipped because the caller was more than FBG_SCHED_MAX_CATCH_UP periods late */
} fbg_scheduler;

/** Start at board time ``t0_us`` with ``rate_mhz`` (> 0, at most 10^9 i.e. 1 MHz). Returns 0, or -1 on a bad rate. */
int fbg_sched_init(fbg_scheduler *s, uint32_t rate_mhz, uint64_t t0_us);

/** Scheduled board time of the next read (microseconds). */
uint64_t fbg_sched_next_us(const fbg_scheduler *s);

/**
 * Called when the caller reads the ADC at board time ``now_us`` (>= fbg_sched_next_us()). Advances
 * the schedule by one read and returns non-zero if this read is late, i.e. ``now_us`` is at or past
 * the following read's time (the sampler missed a deadline: FBG_STATUS_ADC_OVERRUN); the caller then
 * takes the following reads at once to catch up. If more than FBG_SCHED_MAX_CATCH_UP reads are
 * already due, they are skipped instead (no burst): their number is stored in ``*skipped`` (0
 * otherwise; ``skipped`` may be NULL) and added to ``s->skipped``. The board advances its sequence
 * number by the same number, so the host counts the skipped reads as lost samples.
 */
int fbg_sched_take(fbg_scheduler *s, uint64_t now_us, uint32_t *skipped);

#ifdef __cplusplus
}
#endif

#endif
