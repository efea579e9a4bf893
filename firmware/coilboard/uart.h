/* USART0, the host link: 115200 baud 8N1, interrupt-driven, with a ring buffer each way.
 *
 * Receive: the RX interrupt stores bytes; a byte that finds the buffer full is lost and latches the
 * overrun flag (reported as RX_OVERRUN). Transmit: uart_write() queues bytes and the data-register-
 * empty interrupt sends them; it never blocks unless the queue is full.
 */
#ifndef COILBOARD_UART_H
#define COILBOARD_UART_H

#include <stdint.h>

#define UART_BAUD 115200UL

void uart_init(void);

/* Next received byte into *byte; returns 0 when nothing is waiting. */
uint8_t uart_read(uint8_t *byte);

/* 1 when a received byte is waiting (call with interrupts off to decide whether to sleep). */
uint8_t uart_rx_pending(void);

/* Queue n bytes for transmission (waits only while the transmit queue is full). */
void uart_write(const uint8_t *data, uint8_t n);

/* Returns 1 if received bytes were lost since the last call, and clears the flag. */
uint8_t uart_take_overrun(void);

#endif
