/* Simulated AHT10 (see aht10_sim_device.h). */
#include "aht10_sim_device.h"

#include <string.h>

#include "fbg_aht10.h"

void aht10_sim_init(aht10_sim_device *d, const uint64_t *now_us)
{
    memset(d, 0, sizeof *d); /* present, AHT10 (no CRC byte), uncalibrated, idle, no fault windows */
    d->now_us = now_us;
    d->temp_start_cc = 2345;
    d->conversion_us = 75000u;
}

static int fault_active(const aht10_sim_device *d, int kind, uint64_t t)
{
    int i;
    for (i = 0; i < d->n_windows; i++) {
        if (d->windows[i].kind == kind && t >= d->windows[i].start_us && t < d->windows[i].end_us) {
            return 1;
        }
    }
    return 0;
}

uint32_t aht10_sim_cc_to_raw(int64_t cc)
{
    int64_t raw = ((cc + 5000) * (int64_t)(1 << 20)) / 20000;
    if (raw < 0) {
        raw = 0;
    }
    if (raw > 0xFFFFF) {
        raw = 0xFFFFF;
    }
    return (uint32_t)raw;
}

static int64_t temp_at(const aht10_sim_device *d, uint64_t t_us)
{
    /* cc(t) = start + slope * t, t in us; integer, truncated toward zero */
    return d->temp_start_cc + (d->temp_slope_cc_per_s * (int64_t)t_us) / 1000000;
}

int aht10_sim_write(void *ctx, uint8_t addr, const uint8_t *data, size_t n)
{
    aht10_sim_device *d = (aht10_sim_device *)ctx;
    uint64_t now = *d->now_us;
    d->writes++;
    if (addr != FBG_AHT10_ADDR || d->absent || fault_active(d, SIM_FAULT_NACK, now) || n == 0) {
        d->nacks++;
        return 1;
    }
    switch (data[0]) {
    case 0xE1: /* initialisation: calibration enable */
        d->calibrated = 1;
        break;
    case 0xAC: /* trigger measurement */
        d->converting = 1;
        d->conv_start_us = now;
        d->conv_end_us = now + d->conversion_us;
        break;
    case 0xBA: /* soft reset */
        d->converting = 0;
        break;
    default:
        break;
    }
    return 0;
}

int aht10_sim_read(void *ctx, uint8_t addr, uint8_t *data, size_t n)
{
    aht10_sim_device *d = (aht10_sim_device *)ctx;
    uint64_t now = *d->now_us;
    uint8_t b[7];
    size_t i;
    int busy;
    uint32_t raw_h = 0x80000u; /* 50 %RH */
    d->reads++;
    if (addr != FBG_AHT10_ADDR || d->absent || fault_active(d, SIM_FAULT_NACK, now)) {
        d->nacks++;
        return 1;
    }
    if (fault_active(d, SIM_FAULT_ONES, now)) {
        for (i = 0; i < n; i++) {
            data[i] = 0xFFu;
        }
        return 0;
    }
    busy = (d->converting && now < d->conv_end_us) || fault_active(d, SIM_FAULT_BUSY, now);
    if (d->converting && now >= d->conv_end_us && !fault_active(d, SIM_FAULT_BUSY, now)) {
        int64_t cc = fault_active(d, SIM_FAULT_RANGE, d->conv_start_us) ? 9000 : temp_at(d, d->conv_start_us);
        d->raw_t = aht10_sim_cc_to_raw(cc);
        d->converting = 0;
    }
    b[0] = (uint8_t)((busy ? 0x80u : 0u) | ((d->calibrated && !fault_active(d, SIM_FAULT_UNCAL, now)) ? 0x08u : 0u) | 0x10u);
    b[1] = (uint8_t)(raw_h >> 12);
    b[2] = (uint8_t)(raw_h >> 4);
    b[3] = (uint8_t)(((raw_h & 0xFu) << 4) | ((d->raw_t >> 16) & 0xFu));
    b[4] = (uint8_t)(d->raw_t >> 8);
    b[5] = (uint8_t)d->raw_t;
    b[6] = fbg_aht10_crc8(b, 6);
    if (fault_active(d, SIM_FAULT_BADCRC, now)) {
        b[6] ^= 0x5Au;
    }
    if (!d->send_crc && n > 6) {
        n = 6; /* an AHT10 has no 7th byte: the master would read 0xFF */
        data[6] = 0xFFu;
    }
    for (i = 0; i < n && i < 7; i++) {
        data[i] = b[i];
    }
    return 0;
}
