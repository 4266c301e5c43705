/*
 * Board protocol versions 1 and 2 (docs/protocol.md): frame layout, CRC-16/CCITT-FALSE, status bits.
 * Version 2 appends the auxiliary ADC channel ``aux`` (the reference transducer of a dynamic
 * calibration, sampled with the same clock) after the version-1 body.
 *
 * Portable C99: no Arduino or ESP-IDF headers. The encoder writes the fields byte by byte in
 * little-endian order, so it is independent of the host's byte order and of struct packing.
 */
#ifndef FBG_FRAME_H
#define FBG_FRAME_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define FBG_SYNC0 0xA5u
#define FBG_SYNC1 0x5Au
#define FBG_PROTOCOL_VERSION 1u
#define FBG_HEADER_SIZE 4u
#define FBG_BODY_LEN_V1 21u
#define FBG_CRC_SIZE 2u
#define FBG_FRAME_SIZE_V1 (FBG_HEADER_SIZE + FBG_BODY_LEN_V1 + FBG_CRC_SIZE) /* 27 bytes */
#define FBG_PROTOCOL_VERSION_V2 2u
#define FBG_BODY_LEN_V2 23u                                                  /* v1 body + aux (u16) */
#define FBG_FRAME_SIZE_V2 (FBG_HEADER_SIZE + FBG_BODY_LEN_V2 + FBG_CRC_SIZE) /* 29 bytes */
#define FBG_ADC_MAX 4095u                                                    /* 12-bit full scale */

/* Status bits of protocol v1 (docs/protocol.md section 2). Version 1 has no saturation bit:
 * saturation is detected on the host from the counts (0 or 4095). Bits 4..7 are reserved (0). */
#define FBG_STATUS_TEMP_VALID 0x01u   /* temp_cc holds the latest AHT10 reading and it was good */
#define FBG_STATUS_TEMP_PRESENT 0x02u /* the AHT10 answered on I2C at boot */
#define FBG_STATUS_ADC_OVERRUN 0x04u  /* this sample was taken late (t_us is still its true time) */
#define FBG_STATUS_BOOT 0x08u         /* first frame DELIVERED after a (re)boot (fbg_link_on_send) */

/** One board sample, the body of a version-1 frame. */
typedef struct {
    uint16_t seq;    /**< sample sequence number, wraps 65535 -> 0 */
    uint64_t t_us;   /**< board clock at the sample, microseconds since boot */
    uint16_t ref;    /**< ADC counts, reference photodetector, 0..4095 */
    uint16_t x;      /**< ADC counts, x channel, 0..4095 */
    uint16_t y;      /**< ADC counts, y channel, 0..4095 */
    uint16_t z;      /**< ADC counts, z channel, 0..4095 */
    int16_t temp_cc; /**< AHT10 temperature, 0.01 degC */
    uint8_t status;  /**< FBG_STATUS_* bits */
} fbg_sample;

/** CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, not reflected, no final XOR ("123456789" -> 0x29B1). */
uint16_t fbg_crc16_ccitt_false(const uint8_t *data, size_t n);

/** Write the 27-byte version-1 frame of ``s`` into ``out``; returns FBG_FRAME_SIZE_V1. */
size_t fbg_frame_encode_v1(const fbg_sample *s, uint8_t out[FBG_FRAME_SIZE_V1]);

/** Write the 29-byte version-2 frame of ``s`` with the auxiliary channel's ``aux`` counts (0..4095)
 * into ``out``; the CRC covers version..aux. Returns FBG_FRAME_SIZE_V2. */
size_t fbg_frame_encode_v2(const fbg_sample *s, uint16_t aux, uint8_t out[FBG_FRAME_SIZE_V2]);

/** Offset of the status byte in a frame of either version (header, then seq..temp_cc of the v1 body). */
#define FBG_STATUS_OFFSET (FBG_HEADER_SIZE + 20u)

/**
 * Set ``bits`` in the status byte of an encoded frame and recompute its CRC, in place. ``frame`` must
 * be one whole version-1 or version-2 frame of ``size`` bytes (sync, version and body_len consistent
 * with ``size``); returns 0, or -1 for anything else (the buffer is then left unchanged).
 */
int fbg_frame_set_status_bits(uint8_t *frame, size_t size, uint8_t bits);

#ifdef __cplusplus
}
#endif

#endif
