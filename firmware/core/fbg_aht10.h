/*
 * AHT10 temperature measurement as a non-blocking state machine (portable C99).
 *
 * Sensor facts used (Aosong AHT10 datasheet; AHT20 datasheet for the CRC byte):
 *  - I2C address 0x38; after power-up the sensor needs up to 20 ms (AHT10; 40 ms for AHT20)
 *    before it accepts commands; initialisation command 0xE1 0x08 0x00 sets the calibration
 *    enable bit (status bit 3).
 *  - Measurement: trigger 0xAC 0x33 0x00, conversion takes more than 75 ms; reading returns
 *    status, 20 bits humidity, 20 bits temperature S_T (6 bytes). Status bit 7 = busy.
 *  - T [degC] = S_T / 2^20 * 200 - 50; operating range -40..85 degC; soft reset 0xBA.
 *  - AHT20/AHT21 (drop-in, same address and commands) append a 7th byte, CRC-8 with polynomial
 *    x^8 + x^5 + x^4 + 1 (0x31), initial value 0xFF over the 6 data bytes. The AHT10 sends no
 *    CRC, so the check is a configuration option (``check_crc``).
 *
 * The state machine never blocks: every fbg_aht10_poll() call does at most one short I2C
 * transaction and returns, so it can run in a low-priority task beside the sampler. The sampler
 * only reads ``temp_cc`` and the status bits (fbg_aht10_status_bits).
 *
 * Outcome of a measurement (reason codes FBG_AHT10_*):
 *  - good reading: temp_cc updated, TEMP_VALID set;
 *  - NACK on trigger or read, busy after ``busy_timeout_us`` (stuck: a soft reset is sent), bad
 *    CRC-8, calibration bit clear, all-ones bytes (bus stuck high), temperature outside -40..85 degC:
 *    TEMP_VALID cleared, temp_cc keeps the last good value;
 *  - no answer to the initialisation at boot (absent): TEMP_PRESENT and TEMP_VALID clear,
 *    temp_cc 0, and the sensor is not polled again until the next boot (docs/protocol.md s. 2).
 */
#ifndef FBG_AHT10_H
#define FBG_AHT10_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define FBG_AHT10_ADDR 0x38u
#define FBG_AHT10_TEMP_MIN_CC (-4000)
#define FBG_AHT10_TEMP_MAX_CC 8500

/** I2C access supplied by the hardware layer (Wire on the ESP32, a simulated device on the host).
 * Both return 0 on success and non-zero on NACK or bus error. */
typedef struct {
    int (*write)(void *ctx, uint8_t addr, const uint8_t *data, size_t n);
    int (*read)(void *ctx, uint8_t addr, uint8_t *data, size_t n);
    void *ctx;
} fbg_i2c_bus;

typedef struct {
    uint32_t powerup_us;      /**< wait after boot before the first command (datasheet: 20 ms AHT10, 40 ms AHT20) */
    uint32_t period_us;       /**< one measurement every period (drift-free, from the first trigger) */
    uint32_t conversion_us;   /**< wait after the trigger before the first read (datasheet: > 75 ms) */
    uint32_t busy_poll_us;    /**< re-read interval while the busy bit is set */
    uint32_t busy_timeout_us; /**< busy this long after the trigger: the sensor is stuck */
    uint8_t init_attempts;    /**< initialisation attempts at boot before declaring the sensor absent */
    uint8_t check_crc;        /**< 1: read 7 bytes and check the CRC-8 (AHT20/AHT21); 0: AHT10, 6 bytes */
} fbg_aht10_config;

/** Reason of the last completed measurement (or why none is made). */
enum {
    FBG_AHT10_OK = 0,
    FBG_AHT10_NONE_YET,     /* no measurement completed since boot */
    FBG_AHT10_ABSENT,       /* no answer at boot */
    FBG_AHT10_NACK,         /* NACK on trigger or read */
    FBG_AHT10_STUCK,        /* busy bit still set busy_timeout_us after the trigger */
    FBG_AHT10_BAD_CRC,      /* CRC-8 mismatch (check_crc only) */
    FBG_AHT10_UNCALIBRATED, /* calibration-enable bit clear: re-initialised before the next trigger */
    FBG_AHT10_BUS_STUCK,    /* all bytes 0xFF */
    FBG_AHT10_OUT_OF_RANGE, /* temperature outside -40..85 degC */
    FBG_AHT10_REASONS
};

typedef enum {
    FBG_AHT10_S_POWERUP,
    FBG_AHT10_S_INIT,
    FBG_AHT10_S_IDLE,
    FBG_AHT10_S_CONVERTING,
    FBG_AHT10_S_ABSENT
} fbg_aht10_state;

typedef struct {
    fbg_aht10_config cfg;
    fbg_aht10_state state;
    uint64_t wake_us;      /**< board time of the next action */
    uint64_t trigger_us;   /**< board time of the last trigger */
    uint64_t next_trigger_us;
    uint8_t init_tries;
    uint8_t present;       /**< answered the initialisation at boot */
    uint8_t valid;         /**< last measurement good */
    uint8_t need_init;     /**< send the initialisation command before the next trigger */
    int16_t temp_cc;       /**< last good reading, 0.01 degC (0 until the first) */
    uint32_t last_raw;     /**< S_T of the last frame read (20 bits) */
    int last_reason;       /**< FBG_AHT10_* */
    uint32_t counts[FBG_AHT10_REASONS]; /**< completed measurements by outcome */
} fbg_aht10;

/** Defaults: powerup 40 ms, period 500 ms (the simulator's aht10.read_rate_hz = 2), conversion 80 ms,
 * busy poll 10 ms, busy timeout 200 ms, 3 init attempts, no CRC (AHT10). */
fbg_aht10_config fbg_aht10_default_config(void);

/** Power-up state at board time ``now_us``. */
void fbg_aht10_init(fbg_aht10 *a, const fbg_aht10_config *cfg, uint64_t now_us);

/** Advance the state machine at board time ``now_us``: at most one I2C transaction. Returns the
 * board time at which it next wants to be polled. */
uint64_t fbg_aht10_poll(fbg_aht10 *a, const fbg_i2c_bus *bus, uint64_t now_us);

/** FBG_STATUS_TEMP_PRESENT / FBG_STATUS_TEMP_VALID bits for the frames. */
uint8_t fbg_aht10_status_bits(const fbg_aht10 *a);

/** Temperature for the frames, 0.01 degC: last good reading (0 if absent or none yet). */
int16_t fbg_aht10_temp_cc(const fbg_aht10 *a);

/** S_T (20-bit raw temperature) to 0.01 degC: round(S_T * 20000 / 2^20) - 5000, halves rounded up. */
int32_t fbg_aht10_raw_to_cc(uint32_t raw_t);

/** CRC-8 of the AHT20 family: poly 0x31, init 0xFF, not reflected, no final XOR. */
uint8_t fbg_aht10_crc8(const uint8_t *data, size_t n);

#ifdef __cplusplus
}
#endif

#endif
