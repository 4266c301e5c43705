/*
 * Simulated AHT10 on a simulated I2C bus, for fbg_board_host. Behaviour follows the datasheet facts
 * listed in firmware/core/fbg_aht10.h (75 ms conversion, busy bit 7, calibration bit 3, 20-bit
 * S_T = (T + 50) / 200 * 2^20), plus injectable faults in board-time windows.
 */
#ifndef AHT10_SIM_DEVICE_H
#define AHT10_SIM_DEVICE_H

#include <stddef.h>
#include <stdint.h>

enum { SIM_FAULT_NACK, SIM_FAULT_BUSY, SIM_FAULT_BADCRC, SIM_FAULT_RANGE, SIM_FAULT_UNCAL, SIM_FAULT_ONES, SIM_FAULT_KINDS };

#define SIM_MAX_WINDOWS 16

typedef struct {
    int kind;
    uint64_t start_us, end_us;
} sim_fault_window;

typedef struct {
    const uint64_t *now_us;  /* the simulated board clock */
    int absent;              /* never acknowledges */
    int send_crc;            /* AHT20-style 7th byte */
    int64_t temp_start_cc;   /* device temperature at t = 0, 0.01 degC */
    int64_t temp_slope_cc_per_s;
    uint32_t conversion_us;  /* datasheet: 75 ms */
    int calibrated;
    uint64_t conv_start_us, conv_end_us;
    int converting;
    uint32_t raw_t;          /* S_T latched at the end of the last conversion */
    sim_fault_window windows[SIM_MAX_WINDOWS];
    int n_windows;
    uint32_t writes, reads, nacks;
} aht10_sim_device;

void aht10_sim_init(aht10_sim_device *d, const uint64_t *now_us);
int aht10_sim_write(void *ctx, uint8_t addr, const uint8_t *data, size_t n);
int aht10_sim_read(void *ctx, uint8_t addr, uint8_t *data, size_t n);
/** S_T of a temperature in 0.01 degC: floor((cc + 5000) * 2^20 / 20000), clipped to 20 bits. */
uint32_t aht10_sim_cc_to_raw(int64_t cc);

#endif
