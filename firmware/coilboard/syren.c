/* SyRen bus software UART on PD3; see syren.h. */
#include "syren.h"

#include <avr/interrupt.h>
#include <avr/io.h>
#include <util/atomic.h>

#define QUEUE_SIZE 32 /* power of two; eight packets */
#define BIT_CYCLES ((F_CPU + SYREN_BAUD / 2) / SYREN_BAUD)

static volatile uint8_t queue[QUEUE_SIZE];
static volatile uint8_t q_head, q_tail;
static volatile uint8_t shifting; /* the byte on the wire, shifted right as bits go out */
static volatile uint8_t bit_no;   /* next slot: 0 start bit, 1..8 data (LSB first), 9 stop bit */
static volatile uint8_t active;

void syren_init(void)
{
	PORTD |= _BV(PD3); /* idle high before the pin becomes an output: no false start bit */
	DDRD |= _BV(PD3);
	TCCR1A = 0;
	TCCR1B = _BV(WGM12) | _BV(CS10); /* CTC on OCR1A, no prescaler */
	OCR1A = BIT_CYCLES - 1;
	TIMSK1 = 0;
}

ISR(TIMER1_COMPA_vect)
{
	/* the pin is written first so the edge jitter is only the interrupt latency */
	if (bit_no == 0) {
		PORTD &= (uint8_t)~_BV(PD3);
	} else if (bit_no <= 8) {
		if (shifting & 1)
			PORTD |= _BV(PD3);
		else
			PORTD &= (uint8_t)~_BV(PD3);
		shifting >>= 1;
	} else if (bit_no == 9) {
		PORTD |= _BV(PD3);
	} else {
		/* the stop bit has lasted one bit time: start the next byte at once, or go quiet */
		if (q_head != q_tail) {
			PORTD &= (uint8_t)~_BV(PD3);
			shifting = queue[q_tail];
			q_tail = (q_tail + 1) & (QUEUE_SIZE - 1);
			bit_no = 1;
		} else {
			TIMSK1 &= (uint8_t)~_BV(OCIE1A);
			active = 0;
		}
		return;
	}
	bit_no++;
}

void syren_write(uint8_t byte)
{
	uint8_t next = (q_head + 1) & (QUEUE_SIZE - 1);
	while (next == q_tail)
		; /* full: the timer interrupt drains it */
	ATOMIC_BLOCK(ATOMIC_RESTORESTATE) {
		if (!active) {
			shifting = byte;
			bit_no = 0;
			active = 1;
			TCNT1 = 0;
			TIFR1 = _BV(OCF1A);
			TIMSK1 |= _BV(OCIE1A);
		} else {
			queue[q_head] = byte;
			q_head = next;
		}
	}
}

void syren_packet(uint8_t address, uint8_t command, uint8_t data)
{
	syren_write(address);
	syren_write(command);
	syren_write(data);
	syren_write((uint8_t)((address + command + data) & 0x7F));
}

void syren_drive(uint8_t address, int8_t c)
{
	if (c < 0)
		syren_packet(address, SYREN_CMD_BACKWARD, (uint8_t)(-c));
	else
		syren_packet(address, SYREN_CMD_FORWARD, (uint8_t)c);
}

uint8_t syren_queued(void)
{
	uint8_t n;
	ATOMIC_BLOCK(ATOMIC_RESTORESTATE) {
		n = (q_head - q_tail) & (QUEUE_SIZE - 1);
	}
	return n;
}

uint8_t syren_idle(void)
{
	uint8_t idle;
	ATOMIC_BLOCK(ATOMIC_RESTORESTATE) {
		idle = !active && q_head == q_tail;
	}
	return idle;
}
