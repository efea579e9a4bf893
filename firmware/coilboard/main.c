/* Coil-board firmware (ATmega328P, 16 MHz): the host link of docs/coilboard-protocol.md in, the
 * SyRen packetized-serial bus to the four coil drivers out.
 *
 * One main loop, no dynamic memory. Interrupts do the byte-level work (USART0 ring buffers, the
 * software UART on PD3, a 1 ms clock on Timer0); the loop parses frames, answers them, runs the link
 * watchdog (200 ms without a valid frame zeroes all four outputs), brings the SyRen bus up (2 s
 * wait, autobaud byte, serial timeouts) and keeps it refreshed, then sleeps until the next
 * interrupt. The AVR watchdog resets the chip if the loop ever stops turning.
 */
#include <avr/interrupt.h>
#include <avr/io.h>
#include <avr/sleep.h>
#include <avr/wdt.h>
#include <util/atomic.h>

#include "frame.h"
#include "syren.h"
#include "uart.h"

#define PROTOCOL_VERSION 1
#define FW_MAJOR 1
#define FW_MINOR 0
#define CHANNELS 4
#define WATCHDOG_MS 200         /* link watchdog: no valid frame for this long zeroes the outputs */
#define SYREN_STARTUP_MS 2000   /* the drivers may take up to 1 s to listen after power-up */
#define SYREN_GAP_MS 20         /* after the autobaud byte, before the first packet */
#define SYREN_REFRESH_MS 100    /* every driver hears its value at least this often */
#define SYREN_TIMEOUT_UNITS 3   /* the drivers' own serial timeout, 3 x 100 ms */
#define SYREN_FIRST_ADDRESS 128 /* coils 0..3 = +x, -x, +y, -y at addresses 128..131 */

enum request { REQ_HELLO = 0x01, REQ_SET = 0x02, REQ_STATUS = 0x03, REQ_STOP = 0x04 };
#ifdef COILBOARD_TEST_HANG
/* Test builds only (make EXTRA_CFLAGS=-DCOILBOARD_TEST_HANG), never flashed: a request that stops the
 * main loop, so a test can watch the AVR watchdog reset the chip. */
#define REQ_TEST_HANG 0x7F
#endif
enum reply { REP_HELLO = 0x81, REP_ACK = 0x82, REP_STATUS = 0x83, REP_ERROR = 0xEE };
enum error_code {
	ERR_BAD_LENGTH = 0x01,
	ERR_UNKNOWN_TYPE = 0x02,
	ERR_BAD_VALUE = 0x03,
	ERR_NO_HELLO = 0x04,
	ERR_BAD_VERSION = 0x05,
};
enum flag {
	FLAG_HANDSHAKEN = 0x01,
	FLAG_WATCHDOG = 0x02,
	FLAG_SYREN_READY = 0x04,
	FLAG_RX_OVERRUN = 0x08,
};
enum syren_phase { BUS_POWER_UP, BUS_AUTOBAUD_SENT, BUS_TIMEOUTS_QUEUED, BUS_RUNNING };

static volatile uint32_t clock_ms; /* Timer0, 1 kHz */

static struct board {
	int8_t outputs[CHANNELS];
	uint8_t dirty;         /* bit i: driver i must hear its value (changed, refresh or forced) */
	uint8_t next_driver;   /* round robin over the dirty drivers */
	uint8_t flags;         /* HANDSHAKEN, WATCHDOG, SYREN_READY, RX_OVERRUN as reported */
	uint8_t link_armed;    /* a valid frame arrived since power-up or the last trip */
	uint32_t last_valid_ms;
	uint32_t phase_ms;     /* when the SyRen bus entered its current phase / last refresh */
	uint8_t phase;
	uint16_t good_frames;
	uint16_t bad_frames;
	uint16_t watchdog_trips;
} board;

static struct frame_parser parser;

/* Keep the AVR watchdog from biting again right after the reset it caused (it stays enabled with
 * its shortest period across a watchdog reset on this chip). */
void early_watchdog_off(void) __attribute__((naked, used, section(".init3")));
void early_watchdog_off(void)
{
	MCUSR = 0;
	wdt_disable();
}

ISR(TIMER0_COMPA_vect)
{
	clock_ms++;
}

static uint32_t now_ms(void)
{
	uint32_t t;
	ATOMIC_BLOCK(ATOMIC_RESTORESTATE) {
		t = clock_ms;
	}
	return t;
}

static void clock_init(void)
{
	TCCR0A = _BV(WGM01);              /* CTC */
	TCCR0B = _BV(CS01) | _BV(CS00);   /* 16 MHz / 64 = 250 kHz */
	OCR0A = 249;                      /* 250 counts = 1 ms */
	TIMSK0 = _BV(OCIE0A);
}

static void put_u16(uint8_t *p, uint16_t v)
{
	p[0] = (uint8_t)v;
	p[1] = (uint8_t)(v >> 8);
}

static void send(uint8_t seq, uint8_t type, const uint8_t *payload, uint8_t len)
{
	uint8_t out[FRAME_MAX];
	uart_write(out, frame_encode(out, seq, type, payload, len));
}

static void send_error(uint8_t seq, uint8_t code, uint8_t request_type)
{
	uint8_t payload[2] = {code, request_type};
	send(seq, REP_ERROR, payload, sizeof payload);
}

static void send_ack(uint8_t seq)
{
	uint8_t payload[1 + CHANNELS];
	payload[0] = board.flags;
	for (uint8_t i = 0; i < CHANNELS; i++)
		payload[1 + i] = (uint8_t)board.outputs[i];
	send(seq, REP_ACK, payload, sizeof payload);
}

static void set_outputs(const int8_t *values, uint8_t force)
{
	for (uint8_t i = 0; i < CHANNELS; i++) {
		if (force || board.outputs[i] != values[i])
			board.dirty |= (uint8_t)(1 << i);
		board.outputs[i] = values[i];
	}
}

static void handle_hello(const struct frame *f)
{
	if (f->len != 1) {
		send_error(f->seq, ERR_BAD_LENGTH, f->type);
		return;
	}
	if (f->payload[0] != PROTOCOL_VERSION) {
		board.flags &= (uint8_t)~FLAG_HANDSHAKEN;
		send_error(f->seq, ERR_BAD_VERSION, f->type);
		return;
	}
	board.flags |= FLAG_HANDSHAKEN;
	uint8_t payload[6] = {PROTOCOL_VERSION, FW_MAJOR, FW_MINOR, CHANNELS};
	put_u16(payload + 4, WATCHDOG_MS);
	send(f->seq, REP_HELLO, payload, sizeof payload);
}

static void handle_set(const struct frame *f)
{
	if (f->len != CHANNELS) {
		send_error(f->seq, ERR_BAD_LENGTH, f->type);
		return;
	}
	if (!(board.flags & FLAG_HANDSHAKEN)) {
		send_error(f->seq, ERR_NO_HELLO, f->type);
		return;
	}
	for (uint8_t i = 0; i < CHANNELS; i++) {
		if (f->payload[i] == 0x80) { /* -128 has no magnitude on the SyRen's 0..127 scale */
			send_error(f->seq, ERR_BAD_VALUE, f->type);
			return;
		}
	}
	set_outputs((const int8_t *)f->payload, 0);
	board.flags &= (uint8_t)~FLAG_WATCHDOG;
	send_ack(f->seq);
}

static void handle_status(const struct frame *f)
{
	if (f->len != 0) {
		send_error(f->seq, ERR_BAD_LENGTH, f->type);
		return;
	}
	uint8_t payload[15];
	uint32_t up = now_ms();
	payload[0] = board.flags;
	for (uint8_t i = 0; i < 4; i++)
		payload[1 + i] = (uint8_t)(up >> (8 * i));
	for (uint8_t i = 0; i < CHANNELS; i++)
		payload[5 + i] = (uint8_t)board.outputs[i];
	put_u16(payload + 9, board.good_frames);
	put_u16(payload + 11, board.bad_frames);
	put_u16(payload + 13, board.watchdog_trips);
	send(f->seq, REP_STATUS, payload, sizeof payload);
	board.flags &= (uint8_t)~FLAG_RX_OVERRUN; /* reported once */
}

static void handle_stop(const struct frame *f)
{
	static const int8_t zero[CHANNELS];
	if (f->len != 0) {
		send_error(f->seq, ERR_BAD_LENGTH, f->type);
		return;
	}
	set_outputs(zero, 1); /* a stop is always put on the bus, changed or not */
	send_ack(f->seq);
}

static void handle_frame(const struct frame *f, uint32_t now)
{
	board.good_frames++;
	board.last_valid_ms = now;
	board.link_armed = 1;
	switch (f->type) {
	case REQ_HELLO: handle_hello(f); break;
	case REQ_SET: handle_set(f); break;
	case REQ_STATUS: handle_status(f); break;
	case REQ_STOP: handle_stop(f); break;
#ifdef COILBOARD_TEST_HANG
	case REQ_TEST_HANG:
		for (;;)
			; /* interrupts keep running; only the AVR watchdog gets out of here */
#endif
	default: send_error(f->seq, ERR_UNKNOWN_TYPE, f->type); break;
	}
}

static void drain_frames(uint32_t now)
{
	struct frame f;
	for (;;) {
		enum frame_event ev = frame_parser_next(&parser, &f, (uint16_t)now);
		if (ev == FRAME_NONE)
			return;
		if (ev == FRAME_GOOD)
			handle_frame(&f, now);
		else
			board.bad_frames++; /* a bad CRC, or a partial frame gone stale */
	}
}

static void service_link(uint32_t now)
{
	uint8_t byte;
	drain_frames(now); /* a stale partial frame goes before it can swallow new bytes */
	while (uart_read(&byte)) {
		frame_parser_push(&parser, byte, (uint16_t)now);
		drain_frames(now);
	}
	if (uart_take_overrun())
		board.flags |= FLAG_RX_OVERRUN;
}

static void service_watchdog(uint32_t now)
{
	static const int8_t zero[CHANNELS];
	if (!board.link_armed || (uint32_t)(now - board.last_valid_ms) < WATCHDOG_MS)
		return;
	set_outputs(zero, 1);
	board.flags |= FLAG_WATCHDOG;
	board.watchdog_trips++;
	board.link_armed = 0; /* one trip per silence */
}

static void service_syren(uint32_t now)
{
	switch (board.phase) {
	case BUS_POWER_UP:
		if (now < SYREN_STARTUP_MS)
			return;
		syren_write(SYREN_AUTOBAUD);
		board.phase = BUS_AUTOBAUD_SENT;
		board.phase_ms = now;
		return;
	case BUS_AUTOBAUD_SENT:
		if ((uint32_t)(now - board.phase_ms) < SYREN_GAP_MS)
			return;
		for (uint8_t i = 0; i < CHANNELS; i++)
			syren_packet(SYREN_FIRST_ADDRESS + i, SYREN_CMD_TIMEOUT, SYREN_TIMEOUT_UNITS);
		board.phase = BUS_TIMEOUTS_QUEUED;
		return;
	case BUS_TIMEOUTS_QUEUED:
		if (!syren_idle())
			return;
		board.flags |= FLAG_SYREN_READY;
		board.phase = BUS_RUNNING;
		board.phase_ms = now;
		board.dirty = (1 << CHANNELS) - 1; /* whatever a SET asked for meanwhile */
		return;
	default:
		break;
	}
	if ((uint32_t)(now - board.phase_ms) >= SYREN_REFRESH_MS) {
		board.phase_ms = now;
		board.dirty = (1 << CHANNELS) - 1;
	}
	/* one packet ahead at most, so a new value waits behind at most one old packet */
	if (!board.dirty || syren_queued() != 0)
		return;
	for (uint8_t k = 0; k < CHANNELS; k++) {
		uint8_t i = (uint8_t)((board.next_driver + k) % CHANNELS);
		if (board.dirty & (1 << i)) {
			board.dirty &= (uint8_t)~(1 << i);
			syren_drive(SYREN_FIRST_ADDRESS + i, board.outputs[i]);
			board.next_driver = (uint8_t)((i + 1) % CHANNELS);
			return;
		}
	}
}

int main(void)
{
	syren_init();
	uart_init();
	clock_init();
	frame_parser_init(&parser);
	wdt_enable(WDTO_250MS);
	set_sleep_mode(SLEEP_MODE_IDLE);
	sei();
	for (;;) {
		wdt_reset();
		uint32_t now = now_ms();
		service_link(now);
		service_watchdog(now);
		service_syren(now);
		/* sleep until the next interrupt (1 ms clock at the latest); interrupts stay off between
		 * the check and the sleep instruction, so a byte cannot slip in unnoticed */
		cli();
		if (!uart_rx_pending()) {
			sleep_enable();
			sei();
			sleep_cpu();
			sleep_disable();
		}
		sei();
	}
}
