/* The wire protocol's constants (docs/protocol.md, version 1): the one place the firmware takes them
 * from. test/test_firmware_constants.py parses this header and checks every value against
 * cstomo_sensor/board/wire.py, so the two cannot drift apart. Keep one `#define NAME VALUE` per line. */
#ifndef CSTOMO_PROTOCOL_H
#define CSTOMO_PROTOCOL_H

#define CSTOMO_PROTOCOL_VERSION 1
#define CSTOMO_N_ELECTRODES 16
#define CSTOMO_N_VALUES 208
#define CSTOMO_N_PAIRS 16          /* drive pairs per frame */
#define CSTOMO_N_MEASURE 13        /* measurement pairs per drive pair */

/* packet layout (section 1.3) */
#define CSTOMO_HEADER_LEN 4        /* u8 version, u8 type, u16 payload length */
#define CSTOMO_CRC_LEN 4
#define CSTOMO_MAX_PACKET 1024     /* decoded packet: header + payload + crc */
#define CSTOMO_MAX_ENCODED 1030    /* COBS worst case of MAX_PACKET plus the two delimiters */

/* message types (section 1.5) */
#define CSTOMO_MSG_IDENTIFY 0x01
#define CSTOMO_MSG_START 0x02
#define CSTOMO_MSG_STOP 0x03
#define CSTOMO_MSG_SET_CURRENT 0x04
#define CSTOMO_MSG_SET_PATTERN 0x05
#define CSTOMO_MSG_IDENTITY 0x81
#define CSTOMO_MSG_ACK 0x82
#define CSTOMO_MSG_ERROR 0x83
#define CSTOMO_MSG_DATA 0x90

/* error codes */
#define CSTOMO_ERR_UNKNOWN_COMMAND 1
#define CSTOMO_ERR_BAD_ARGUMENT 2
#define CSTOMO_ERR_NOT_SUPPORTED 3
#define CSTOMO_ERR_BAD_VERSION 4

/* payloads */
#define CSTOMO_IDENTITY_HEAD_LEN 5 /* u16 protocol version, u8 electrodes, u16 values per frame */
#define CSTOMO_MAX_FIRMWARE_TEXT 64
#define CSTOMO_MAX_ERROR_TEXT 200
#define CSTOMO_SAT_BYTES 26        /* 208 saturation bits */
#define CSTOMO_DATA_HEAD_LEN 14    /* u32 seq, u64 board_time_us, u16 contact */
#define CSTOMO_DATA_LEN 872        /* DATA payload */
#define CSTOMO_DATA_PACKET 880     /* header + DATA payload + crc */
#define CSTOMO_DATA_WIRE_BYTES 886 /* a DATA frame on the wire at most (section 1.9) */
#define CSTOMO_BITS_PER_BYTE 10    /* 8N1 */

/* the reference board */
#define CSTOMO_DRIVE_CURRENT_A 0.008f
#define CSTOMO_PATTERN_ONE_RING 1
#define CSTOMO_PATTERN_TWO_RINGS 2

#endif
