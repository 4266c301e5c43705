/* AHT10 non-blocking measurement state machine (see fbg_aht10.h for the datasheet facts used). */
#include "fbg_aht10.h"

#include "fbg_frame.h"

static const uint8_t CMD_INIT[3] = {0xE1u, 0x08u, 0x00u};
static const uint8_t CMD_TRIGGER[3] = {0xACu, 0x33u, 0x00u};
static const uint8_t CMD_SOFT_RESET[1] = {0xBAu};

#define STATUS_BUSY 0x80u
#define STATUS_CALIBRATED 0x08u

fbg_aht10_config fbg_aht10_default_config(void)
{
    fbg_aht10_config c;
    c.powerup_us = 40000u;
    c.period_us = 500000u;
    c.conversion_us = 80000u;
    c.busy_poll_us = 10000u;
    c.busy_timeout_us = 200000u;
    c.init_attempts = 3u;
    c.check_crc = 0u;
    return c;
}

void fbg_aht10_init(fbg_aht10 *a, const fbg_aht10_config *cfg, uint64_t now_us)
{
    int i;
    a->cfg = *cfg;
    a->state = FBG_AHT10_S_POWERUP;
    a->wake_us = now_us + cfg->powerup_us;
    a->trigger_us = 0;
    a->next_trigger_us = 0;
    a->init_tries = 0;
    a->present = 0;
    a->valid = 0;
    a->need_init = 0;
    a->temp_cc = 0;
    a->last_raw = 0;
    a->last_reason = FBG_AHT10_NONE_YET;
    for (i = 0; i < FBG_AHT10_REASONS; i++) {
        a->counts[i] = 0;
    }
}

uint8_t fbg_aht10_crc8(const uint8_t *data, size_t n)
{
    uint8_t crc = 0xFFu;
    size_t i;
    int bit;
    for (i = 0; i < n; i++) {
        crc ^= data[i];
        for (bit = 0; bit < 8; bit++) {
            crc = (crc & 0x80u) ? (uint8_t)((crc << 1) ^ 0x31u) : (uint8_t)(crc << 1);
        }
    }
    return crc;
}

int32_t fbg_aht10_raw_to_cc(uint32_t raw_t)
{
    /* T*100 = S_T * 20000 / 2^20 - 5000; 20000 * (2^20 - 1) needs 35 bits. */
    uint64_t scaled = (uint64_t)(raw_t & 0xFFFFFu) * 20000u;
    return (int32_t)((scaled + (1u << 19)) >> 20) - 5000;
}

/* Schedule the next trigger on the drift-free grid, skipping slots already in the past. */
static void schedule_next(fbg_aht10 *a, uint64_t now_us)
{
    do {
        a->next_trigger_us += a->cfg.period_us;
    } while (a->next_trigger_us <= now_us);
    a->state = FBG_AHT10_S_IDLE;
    a->wake_us = a->next_trigger_us;
}

static void finish(fbg_aht10 *a, int reason, uint64_t now_us)
{
    a->last_reason = reason;
    a->counts[reason]++;
    a->valid = (uint8_t)(reason == FBG_AHT10_OK);
    schedule_next(a, now_us);
}

static void read_measurement(fbg_aht10 *a, const fbg_i2c_bus *bus, uint64_t now_us)
{
    uint8_t d[7];
    size_t n = a->cfg.check_crc ? 7u : 6u;
    size_t i;
    int all_ones = 1;
    uint32_t raw;
    int32_t cc;
    if (bus->read(bus->ctx, FBG_AHT10_ADDR, d, n) != 0) {
        finish(a, FBG_AHT10_NACK, now_us);
        return;
    }
    for (i = 0; i < n; i++) {
        all_ones &= (d[i] == 0xFFu);
    }
    if (all_ones) {
        finish(a, FBG_AHT10_BUS_STUCK, now_us);
        return;
    }
    if (d[0] & STATUS_BUSY) {
        if (now_us - a->trigger_us >= a->cfg.busy_timeout_us) {
            (void)bus->write(bus->ctx, FBG_AHT10_ADDR, CMD_SOFT_RESET, sizeof CMD_SOFT_RESET);
            a->need_init = 1;
            finish(a, FBG_AHT10_STUCK, now_us);
        } else {
            a->wake_us = now_us + a->cfg.busy_poll_us;
        }
        return;
    }
    if (a->cfg.check_crc && fbg_aht10_crc8(d, 6) != d[6]) {
        finish(a, FBG_AHT10_BAD_CRC, now_us);
        return;
    }
    if (!(d[0] & STATUS_CALIBRATED)) {
        a->need_init = 1;
        finish(a, FBG_AHT10_UNCALIBRATED, now_us);
        return;
    }
    raw = ((uint32_t)(d[3] & 0x0Fu) << 16) | ((uint32_t)d[4] << 8) | (uint32_t)d[5];
    a->last_raw = raw;
    cc = fbg_aht10_raw_to_cc(raw);
    if (cc < FBG_AHT10_TEMP_MIN_CC || cc > FBG_AHT10_TEMP_MAX_CC) {
        finish(a, FBG_AHT10_OUT_OF_RANGE, now_us);
        return;
    }
    a->temp_cc = (int16_t)cc;
    finish(a, FBG_AHT10_OK, now_us);
}

uint64_t fbg_aht10_poll(fbg_aht10 *a, const fbg_i2c_bus *bus, uint64_t now_us)
{
    if (a->state == FBG_AHT10_S_ABSENT || now_us < a->wake_us) {
        return a->state == FBG_AHT10_S_ABSENT ? UINT64_MAX : a->wake_us;
    }
    switch (a->state) {
    case FBG_AHT10_S_POWERUP:
        a->state = FBG_AHT10_S_INIT;
        /* fall through */
    case FBG_AHT10_S_INIT:
        a->init_tries++;
        if (bus->write(bus->ctx, FBG_AHT10_ADDR, CMD_INIT, sizeof CMD_INIT) == 0) {
            a->present = 1;
            a->state = FBG_AHT10_S_IDLE;
            a->next_trigger_us = now_us + a->cfg.busy_poll_us; /* first trigger after the init settles */
            a->wake_us = a->next_trigger_us;
        } else if (a->init_tries >= a->cfg.init_attempts) {
            a->state = FBG_AHT10_S_ABSENT;
            a->last_reason = FBG_AHT10_ABSENT;
            a->wake_us = UINT64_MAX;
        } else {
            a->wake_us = now_us + a->cfg.busy_poll_us;
        }
        break;
    case FBG_AHT10_S_IDLE:
        if (a->need_init) { /* after a soft reset or a lost calibration bit; a NACK shows up on the trigger */
            a->need_init = 0;
            (void)bus->write(bus->ctx, FBG_AHT10_ADDR, CMD_INIT, sizeof CMD_INIT);
            a->wake_us = now_us + a->cfg.busy_poll_us;
            break;
        }
        if (bus->write(bus->ctx, FBG_AHT10_ADDR, CMD_TRIGGER, sizeof CMD_TRIGGER) != 0) {
            finish(a, FBG_AHT10_NACK, now_us);
            break;
        }
        a->trigger_us = now_us;
        a->state = FBG_AHT10_S_CONVERTING;
        a->wake_us = now_us + a->cfg.conversion_us;
        break;
    case FBG_AHT10_S_CONVERTING:
        read_measurement(a, bus, now_us);
        break;
    case FBG_AHT10_S_ABSENT:
        break;
    }
    return a->state == FBG_AHT10_S_ABSENT ? UINT64_MAX : a->wake_us;
}

uint8_t fbg_aht10_status_bits(const fbg_aht10 *a)
{
    uint8_t bits = 0;
    if (a->present) {
        bits |= FBG_STATUS_TEMP_PRESENT;
        if (a->valid) {
            bits |= FBG_STATUS_TEMP_VALID;
        }
    }
    return bits;
}

int16_t fbg_aht10_temp_cc(const fbg_aht10 *a)
{
    return a->present ? a->temp_cc : (int16_t)0;
}
