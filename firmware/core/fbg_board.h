/*
 * Board sample assembly: the sequence counter (u16, wraps 65535 -> 0, 0 at boot), the BOOT bit on
 * the first sample after power-up, the ADC range guard and the status byte (docs/protocol.md s. 4).
 * Portable C99.
 */
#ifndef FBG_BOARD_H
#define FBG_BOARD_H

#include <stdint.h>

#include "fbg_frame.h"

#ifdef __cplusplus
extern "C" {
#endif

/** Per-boot state of the sample producer. */
typedef struct {
    uint16_t next_seq;   /**< sequence number of the next sample */
    uint8_t boot_sent;   /**< 0 until the first sample has been produced */
    uint32_t adc_clamps; /**< ADC readings above 4095 clamped (a hardware-layer bug if ever non-zero) */
} fbg_board;

/** Power-up state: next sample has seq 0 and carries BOOT. */
void fbg_board_init(fbg_board *b);

/**
 * Produce the next sample. ``adc`` is {ref, x, y, z} in counts; ``temp_cc`` and ``temp_bits``
 * (FBG_STATUS_TEMP_VALID | FBG_STATUS_TEMP_PRESENT) come from the AHT10 state machine;
 * ``overrun`` is non-zero when the sample was taken late. The sequence number advances once per
 * call, whether or not the caller manages to send the frame (a host-side gap is a real loss).
 */
void fbg_board_next_sample(fbg_board *b, uint64_t t_us, const uint16_t adc[4], int16_t temp_cc, uint8_t temp_bits,
                           int overrun, fbg_sample *out);

/** Account for ``n`` sample slots the sampler skipped (they count as samples the host did not get). */
void fbg_board_skip(fbg_board *b, uint32_t n);

#ifdef __cplusplus
}
#endif

#endif
