/* Drift-free integer sample scheduler (see fbg_scheduler.h). */
#include "fbg_scheduler.h"

#include <stddef.h>

#define US_PER_S_TIMES_1000 1000000000ull /* 10^6 us/s x 10^3 mHz/Hz */

int fbg_sched_init(fbg_scheduler *s, uint32_t rate_mhz, uint64_t t0_us)
{
    if (rate_mhz == 0u || (uint64_t)rate_mhz > US_PER_S_TIMES_1000) {
        return -1;
    }
    s->t0_us = t0_us;
    s->rate_mhz = rate_mhz;
    s->whole_us = US_PER_S_TIMES_1000 / rate_mhz;
    s->rem = (uint32_t)(US_PER_S_TIMES_1000 % rate_mhz);
    s->acc = 0;
    s->index = 0;
    s->next_us = t0_us;
    s->skipped = 0;
    return 0;
}

uint64_t fbg_sched_next_us(const fbg_scheduler *s)
{
    return s->next_us;
}

static void advance(fbg_scheduler *s)
{
    s->next_us += s->whole_us;
    s->acc += s->rem; /* both < rate_mhz <= 10^9 < 2^30: the sum fits in u32 */
    if (s->acc >= s->rate_mhz) {
        s->acc -= s->rate_mhz;
        s->next_us += 1u;
    }
    s->index += 1u;
}

int fbg_sched_take(fbg_scheduler *s, uint64_t now_us, uint32_t *skipped)
{
    fbg_scheduler probe;
    uint32_t due = 0;
    uint32_t n = 0;
    if (skipped != NULL) {
        *skipped = 0;
    }
    advance(s);
    if (now_us < s->next_us) {
        return 0;
    }
    /* Late: count the reads already due, up to one more than the catch-up allowance. */
    probe = *s;
    while (now_us >= probe.next_us && due <= FBG_SCHED_MAX_CATCH_UP) {
        advance(&probe);
        due++;
    }
    if (due > FBG_SCHED_MAX_CATCH_UP) {
        while (now_us >= s->next_us) {
            advance(s);
            n++;
        }
        s->skipped += n;
        if (skipped != NULL) {
            *skipped = n;
        }
    }
    return 1;
}
