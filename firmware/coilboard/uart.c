/* USART0 host link; see uart.h. */
#include "uart.h"

#include <avr/interrupt.h>
#include <avr/io.h>
#include <util/atomic.h>

/* powers of two, so the indices wrap with a mask */
#define RX_SIZE 64
#define TX_SIZE 64

static volatile uint8_t rx_buf[RX_SIZE];
static volatile uint8_t rx_head, rx_tail;
static volatile uint8_t rx_overrun;
static volatile uint8_t tx_buf[TX_SIZE];
static volatile uint8_t tx_head, tx_tail;

void uart_init(void)
{
	/* U2X: 16 MHz / (8 x (16 + 1)) = 117647 baud, 2.1 % fast, as every Uno at 115200 */
	UCSR0A = _BV(U2X0);
	UBRR0H = 0;
	UBRR0L = 16;
	UCSR0C = _BV(UCSZ01) | _BV(UCSZ00); /* 8N1 */
	UCSR0B = _BV(RXEN0) | _BV(TXEN0) | _BV(RXCIE0);
}

ISR(USART_RX_vect)
{
	uint8_t status = UCSR0A;
	uint8_t byte = UDR0;
	uint8_t next = (rx_head + 1) & (RX_SIZE - 1);
	if (status & _BV(DOR0))
		rx_overrun = 1; /* the hardware lost a byte before this one */
	if (next == rx_tail) {
		rx_overrun = 1;
		return;
	}
	rx_buf[rx_head] = byte;
	rx_head = next;
}

ISR(USART_UDRE_vect)
{
	if (tx_head == tx_tail) {
		UCSR0B &= (uint8_t)~_BV(UDRIE0);
		return;
	}
	UDR0 = tx_buf[tx_tail];
	tx_tail = (tx_tail + 1) & (TX_SIZE - 1);
}

uint8_t uart_read(uint8_t *byte)
{
	if (rx_head == rx_tail)
		return 0;
	*byte = rx_buf[rx_tail];
	rx_tail = (rx_tail + 1) & (RX_SIZE - 1);
	return 1;
}

uint8_t uart_rx_pending(void)
{
	return rx_head != rx_tail;
}

void uart_write(const uint8_t *data, uint8_t n)
{
	while (n--) {
		uint8_t next = (tx_head + 1) & (TX_SIZE - 1);
		while (next == tx_tail)
			; /* full: the UDRE interrupt drains it (87 us a byte) */
		tx_buf[tx_head] = *data++;
		tx_head = next;
		UCSR0B |= _BV(UDRIE0);
	}
}

uint8_t uart_take_overrun(void)
{
	uint8_t was;
	ATOMIC_BLOCK(ATOMIC_RESTORESTATE) {
		was = rx_overrun;
		rx_overrun = 0;
	}
	return was;
}
