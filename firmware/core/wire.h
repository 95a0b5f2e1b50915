/* Framing of docs/protocol.md: CRC-32 (zlib), COBS, packets. Pure functions, no state, no heap. */
#ifndef CSTOMO_WIRE_H
#define CSTOMO_WIRE_H

#include <stddef.h>
#include <stdint.h>

/* CRC-32 as zlib / IEEE 802.3: crc32_update(0, "123456789", 9) == 0xCBF43926; chain by passing the
 * previous result as `crc`. */
uint32_t crc32_update(uint32_t crc, const uint8_t *data, size_t n);

/* COBS-encode n bytes into out (room for n + n / 254 + 1 bytes); returns the encoded length. */
size_t cobs_encode(const uint8_t *in, size_t n, uint8_t *out);
/* COBS-decode n bytes (no 0x00 among them) into out (may be `in`: decoding never writes ahead of
 * reading); returns the decoded length, or -1 for input no encoder could have produced. */
long cobs_decode(const uint8_t *in, size_t n, uint8_t *out);

/* Complete a packet in `pkt`: pkt[4..4+len) holds the payload; writes the header (version, type,
 * len) and the CRC after the payload; returns the packet's length (len + 8). */
size_t packet_finish(uint8_t *pkt, uint8_t type, uint16_t len);
/* The wire bytes of a packet: 0x00 COBS(pkt) 0x00 into `wire` (room: n + n / 254 + 3); returns the length. */
size_t packet_to_wire(const uint8_t *pkt, size_t n, uint8_t *wire);

/* little-endian stores and loads */
static inline void put_u16(uint8_t *p, uint16_t v) { p[0] = (uint8_t)v; p[1] = (uint8_t)(v >> 8); }
static inline void put_u32(uint8_t *p, uint32_t v) {
    p[0] = (uint8_t)v; p[1] = (uint8_t)(v >> 8); p[2] = (uint8_t)(v >> 16); p[3] = (uint8_t)(v >> 24);
}
static inline void put_u64(uint8_t *p, uint64_t v) { put_u32(p, (uint32_t)v); put_u32(p + 4, (uint32_t)(v >> 32)); }
static inline uint16_t get_u16(const uint8_t *p) { return (uint16_t)(p[0] | (p[1] << 8)); }
static inline uint32_t get_u32(const uint8_t *p) {
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}
/* IEEE 754 binary32 <-> bits without aliasing trouble */
uint32_t f32_bits(float f);
float f32_from_bits(uint32_t u);

#endif
