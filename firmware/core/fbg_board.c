/* Sample assembly: sequence counter, status byte; BOOT on the first frame delivered (docs/protocol.md s. 2, 4). */
#include "fbg_board.h"

void fbg_board_init(fbg_board *b)
{
    b->next_seq = 0;
    b->adc_clamps = 0;
}

static uint16_t clamp_adc(fbg_board *b, uint16_t v)
{
    if (v > FBG_ADC_MAX) { /* a frame with counts > 4095 is rejected by the host: never send one */
        b->adc_clamps++;
        return (uint16_t)FBG_ADC_MAX;
    }
    return v;
}

void fbg_board_next_sample(fbg_board *b, uint64_t t_us, const uint16_t adc[4], int16_t temp_cc, uint8_t temp_bits,
                           int overrun, fbg_sample *out)
{
    uint8_t status = (uint8_t)(temp_bits & (FBG_STATUS_TEMP_VALID | FBG_STATUS_TEMP_PRESENT));
    if (overrun) {
        status |= FBG_STATUS_ADC_OVERRUN;
    }
    out->seq = b->next_seq;
    b->next_seq = (uint16_t)(b->next_seq + 1u); /* unsigned 16-bit: 65535 + 1 -> 0 */
    out->t_us = t_us;
    out->ref = clamp_adc(b, adc[0]);
    out->x = clamp_adc(b, adc[1]);
    out->y = clamp_adc(b, adc[2]);
    out->z = clamp_adc(b, adc[3]);
    out->temp_cc = temp_cc;
    out->status = status;
}

void fbg_board_skip(fbg_board *b, uint32_t n)
{
    b->next_seq = (uint16_t)(b->next_seq + (uint16_t)(n & 0xFFFFu));
}

void fbg_link_init(fbg_link *l)
{
    l->boot_delivered = 0;
}

int fbg_link_on_send(fbg_link *l, uint8_t *frame, size_t size)
{
    if (l->boot_delivered) {
        return 0;
    }
    if (fbg_frame_set_status_bits(frame, size, FBG_STATUS_BOOT) != 0) {
        return -1;
    }
    l->boot_delivered = 1;
    return 1;
}
