/* Host-link framing and CRC-16/CCITT-FALSE; see frame.h. */
#include "frame.h"

#include <string.h>

uint16_t crc16_ccitt_false(const uint8_t *data, uint8_t n)
{
	uint16_t crc = 0xFFFF;
	while (n--) {
		crc ^= (uint16_t)(*data++) << 8;
		for (uint8_t bit = 0; bit < 8; bit++)
			crc = (crc & 0x8000) ? (uint16_t)((crc << 1) ^ 0x1021) : (uint16_t)(crc << 1);
	}
	return crc;
}

void frame_parser_init(struct frame_parser *p)
{
	p->fill = 0;
}

static void drop_front(struct frame_parser *p, uint8_t n)
{
	memmove(p->buf, p->buf + n, p->fill - n);
	memmove(p->arrived_ms, p->arrived_ms + n, (p->fill - n) * sizeof p->arrived_ms[0]);
	p->fill -= n;
}

void frame_parser_push(struct frame_parser *p, uint8_t byte, uint16_t now_ms)
{
	if (p->fill == 0 && byte != FRAME_SYNC)
		return; /* hunting: anything but SYNC is garbage */
	if (p->fill < FRAME_MAX) {
		p->buf[p->fill] = byte;
		p->arrived_ms[p->fill] = now_ms;
		p->fill++;
	}
}

enum frame_event frame_parser_next(struct frame_parser *p, struct frame *out, uint16_t now_ms)
{
	for (;;) {
		while (p->fill > 0 && p->buf[0] != FRAME_SYNC)
			drop_front(p, 1);
		if (p->fill == 0)
			return FRAME_NONE;
		if (p->fill >= 2 && p->buf[1] > FRAME_MAX_PAYLOAD) {
			drop_front(p, 1); /* not a frame (and not counted): hunt again */
			continue;
		}
		uint8_t total = (uint8_t)(FRAME_OVERHEAD + (p->fill >= 2 ? p->buf[1] : 0));
		if (p->fill < total) {
			if ((uint16_t)(now_ms - p->arrived_ms[0]) <= FRAME_STALE_MS)
				return FRAME_NONE; /* wait for the rest */
			drop_front(p, 1);
			return FRAME_STALE;
		}
		uint8_t len = p->buf[1];
		uint16_t want = crc16_ccitt_false(p->buf + 1, (uint8_t)(3 + len));
		uint16_t got = (uint16_t)p->buf[4 + len] | ((uint16_t)p->buf[5 + len] << 8);
		if (want != got) {
			drop_front(p, 1); /* only the SYNC: a frame may start inside */
			return FRAME_BAD_CRC;
		}
		out->len = len;
		out->seq = p->buf[2];
		out->type = p->buf[3];
		memcpy(out->payload, p->buf + 4, len);
		drop_front(p, total);
		return FRAME_GOOD;
	}
}

uint8_t frame_encode(uint8_t *out, uint8_t seq, uint8_t type, const uint8_t *payload, uint8_t len)
{
	out[0] = FRAME_SYNC;
	out[1] = len;
	out[2] = seq;
	out[3] = type;
	memcpy(out + 4, payload, len);
	uint16_t crc = crc16_ccitt_false(out + 1, (uint8_t)(3 + len));
	out[4 + len] = (uint8_t)(crc & 0xFF);
	out[5 + len] = (uint8_t)(crc >> 8);
	return (uint8_t)(FRAME_OVERHEAD + len);
}
