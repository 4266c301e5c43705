/* Frame encoder of protocol versions 1 and 2 (docs/protocol.md sections 2 and 3). */
#include "fbg_frame.h"

uint16_t fbg_crc16_ccitt_false(const uint8_t *data, size_t n)
{
    uint16_t crc = 0xFFFFu;
    size_t i;
    int bit;
    for (i = 0; i < n; i++) {
        crc ^= (uint16_t)((uint16_t)data[i] << 8);
        for (bit = 0; bit < 8; bit++) {
            crc = (crc & 0x8000u) ? (uint16_t)((crc << 1) ^ 0x1021u) : (uint16_t)(crc << 1);
        }
    }
    return crc;
}

static uint8_t *put_u16(uint8_t *p, uint16_t v)
{
    p[0] = (uint8_t)(v & 0xFFu);
    p[1] = (uint8_t)(v >> 8);
    return p + 2;
}

/* Header and the version-1 body fields; returns the write position (the body continues there). */
static uint8_t *put_head_and_v1_body(const fbg_sample *s, uint8_t version, uint8_t body_len, uint8_t *out)
{
    uint8_t *p = out;
    int i;
    *p++ = FBG_SYNC0;
    *p++ = FBG_SYNC1;
    *p++ = version;
    *p++ = body_len;
    p = put_u16(p, s->seq);
    for (i = 0; i < 8; i++) {
        *p++ = (uint8_t)((s->t_us >> (8 * i)) & 0xFFu);
    }
    p = put_u16(p, s->ref);
    p = put_u16(p, s->x);
    p = put_u16(p, s->y);
    p = put_u16(p, s->z);
    p = put_u16(p, (uint16_t)s->temp_cc); /* two's complement, as int16 little-endian */
    *p++ = s->status;
    return p;
}

/* CRC over version..end of body (every version), low byte first; returns the frame size. */
static size_t put_crc(uint8_t *out, uint8_t *p)
{
    uint16_t crc = fbg_crc16_ccitt_false(out + 2, (size_t)(p - (out + 2)));
    p = put_u16(p, crc);
    return (size_t)(p - out);
}

size_t fbg_frame_encode_v1(const fbg_sample *s, uint8_t out[FBG_FRAME_SIZE_V1])
{
    return put_crc(out, put_head_and_v1_body(s, FBG_PROTOCOL_VERSION, FBG_BODY_LEN_V1, out));
}

size_t fbg_frame_encode_v2(const fbg_sample *s, uint16_t aux, uint8_t out[FBG_FRAME_SIZE_V2])
{
    uint8_t *p = put_head_and_v1_body(s, FBG_PROTOCOL_VERSION_V2, FBG_BODY_LEN_V2, out);
    p = put_u16(p, aux > FBG_ADC_MAX ? (uint16_t)FBG_ADC_MAX : aux); /* 12-bit: the decoder refuses more */
    return put_crc(out, p);
}

int fbg_frame_set_status_bits(uint8_t *frame, size_t size, uint8_t bits)
{
    size_t body_len;
    if (frame == NULL || size < FBG_FRAME_SIZE_V1 || frame[0] != FBG_SYNC0 || frame[1] != FBG_SYNC1) {
        return -1;
    }
    body_len = frame[3];
    if (!((frame[2] == FBG_PROTOCOL_VERSION && body_len == FBG_BODY_LEN_V1) ||
          (frame[2] == FBG_PROTOCOL_VERSION_V2 && body_len == FBG_BODY_LEN_V2)) ||
        size != FBG_HEADER_SIZE + body_len + FBG_CRC_SIZE) {
        return -1;
    }
    frame[FBG_STATUS_OFFSET] |= bits;
    (void)put_crc(frame, frame + FBG_HEADER_SIZE + body_len);
    return 0;
}
