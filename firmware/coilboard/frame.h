/* Host-link framing (docs/coilboard-protocol.md, "Frame"): SYNC, LEN, SEQ, TYPE, PAYLOAD, CRC.
 *
 * The parser is fed one byte at a time with the millisecond clock; it hunts for SYNC, rejects a LEN
 * above FRAME_MAX_PAYLOAD, checks the CRC-16/CCITT-FALSE over LEN..PAYLOAD and, on a bad CRC, drops
 * only the SYNC byte and rescans the bytes it already holds, so it resynchronises within one frame.
 * A partial frame whose SYNC arrived more than FRAME_STALE_MS ago loses its SYNC the same way, so a
 * stray SYNC can hold back a real frame behind it by at most that long. Each byte keeps its own
 * arrival time (16 bits of the millisecond clock are plenty for a 20 ms rule).
 */
#ifndef COILBOARD_FRAME_H
#define COILBOARD_FRAME_H

#include <stdint.h>

#define FRAME_SYNC 0xA5
#define FRAME_MAX_PAYLOAD 16
#define FRAME_OVERHEAD 6 /* SYNC, LEN, SEQ, TYPE, CRC lo, CRC hi */
#define FRAME_MAX (FRAME_OVERHEAD + FRAME_MAX_PAYLOAD)
#define FRAME_STALE_MS 20

struct frame {
	uint8_t seq;
	uint8_t type;
	uint8_t len;
	uint8_t payload[FRAME_MAX_PAYLOAD];
};

enum frame_event {
	FRAME_NONE,      /* nothing complete yet */
	FRAME_GOOD,      /* a frame with a good CRC is in the output */
	FRAME_BAD_CRC,   /* a candidate frame failed its CRC (counted, never answered) */
	FRAME_STALE,     /* a partial frame waited too long; its SYNC was dropped (counted) */
};

struct frame_parser {
	uint8_t buf[FRAME_MAX];
	uint16_t arrived_ms[FRAME_MAX];
	uint8_t fill;
};

uint16_t crc16_ccitt_false(const uint8_t *data, uint8_t n);

void frame_parser_init(struct frame_parser *p);

/* Append one received byte; then call frame_parser_next() until it returns FRAME_NONE. */
void frame_parser_push(struct frame_parser *p, uint8_t byte, uint16_t now_ms);

/* Scan what is buffered at time now_ms: FRAME_GOOD (with *out filled), FRAME_BAD_CRC, FRAME_STALE,
 * or FRAME_NONE. Call it until FRAME_NONE before pushing new bytes too, so that a stale partial
 * frame is dropped before it can swallow them. */
enum frame_event frame_parser_next(struct frame_parser *p, struct frame *out, uint16_t now_ms);

/* Encode a frame into out (at least FRAME_OVERHEAD + len bytes); returns its length. */
uint8_t frame_encode(uint8_t *out, uint8_t seq, uint8_t type, const uint8_t *payload, uint8_t len);

#endif
