/*
 * Board sample assembly: the sequence counter (u16, wraps 65535 -> 0, 0 at boot), the ADC range
 * guard and the status byte (docs/protocol.md s. 4); and, on the writer's side, the BOOT bit on the
 * first frame DELIVERED after power-up (fbg_link_on_send). Portable C99.
 */
#ifndef FBG_BOARD_H
#define FBG_BOARD_H

#include <stddef.h>
#include <stdint.h>

#include "fbg_frame.h"

#ifdef __cplusplus
extern "C" {
#endif

/** Per-boot state of the sample producer. */
typedef struct {
    uint16_t next_seq;   /**< sequence number of the next sample */
    uint32_t adc_clamps; /**< ADC readings above 4095 clamped (a hardware-layer bug if ever non-zero) */
} fbg_board;

/** Power-up state: next sample has seq 0. The sample producer never sets BOOT (see fbg_link_on_send). */
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

/**
 * Writer-side state of the BOOT bit. BOOT means "the first frame delivered after power-up", not the
 * first sample produced: a writer that discards frames while its link is down (Bluetooth SPP with no
 * client, firmware/esp32/fbg_board/fbg_board.ino writer_task) would otherwise discard the only frame
 * with BOOT, and a reboot after a short uptime would be invisible to the host (docs/protocol.md s. 4).
 */
typedef struct {
    uint8_t boot_delivered; /**< 0 until the first frame after power-up has been handed to the link */
} fbg_link;

/** Power-up state: the next frame sent carries BOOT. Also re-arms BOOT if that frame did not go out whole. */
void fbg_link_init(fbg_link *l);

/**
 * Call on each frame the writer is about to send (never on a frame it discards). The first one after
 * power-up gets the BOOT bit and a recomputed CRC (the sequence number is whatever the sampler had
 * reached: frames discarded before are not counted as lost by the host, see docs/protocol.md s. 4);
 * no later frame does. Returns 1 if BOOT was set on this frame, 0 if not, -1 if ``frame`` is not one
 * whole version-1 or version-2 frame of ``size`` bytes (left unchanged, BOOT still pending).
 */
int fbg_link_on_send(fbg_link *l, uint8_t *frame, size_t size);

#ifdef __cplusplus
}
#endif

#endif
