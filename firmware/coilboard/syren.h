/* The SyRen bus: a transmit-only software UART on PD3 (Arduino pin 3), 9600 baud 8N1, shared by
 * the four SyRen drivers in Packetized Serial mode (Dimension Engineering, SyRen 10/25 manual,
 * "Mode 4: Packetized Serial").
 *
 * Timer1 in CTC mode interrupts once per bit (16 MHz / 1667 = 9598 baud, 0.02 % slow) and drives the
 * pin; the interrupt is enabled only while bytes are going out, so an idle bus costs nothing. A
 * packet is address (128..135), command, data (0..127), checksum = (address + command + data) & 0x7F.
 */
#ifndef COILBOARD_SYREN_H
#define COILBOARD_SYREN_H

#include <stdint.h>

#define SYREN_BAUD 9600UL
#define SYREN_AUTOBAUD 0xAA     /* sent once, first, so the drivers measure the baud rate */
#define SYREN_CMD_FORWARD 0     /* data 0..127: off .. full forward */
#define SYREN_CMD_BACKWARD 1    /* data 0..127: off .. full reverse */
#define SYREN_CMD_TIMEOUT 14    /* data: serial timeout in 100 ms units, 0 disables */

/* Drive PD3 high (the idle level) and set up Timer1; call before interrupts are enabled. */
void syren_init(void);

/* Queue one byte; waits only if the queue is full. */
void syren_write(uint8_t byte);

/* Queue one packet (four bytes, checksum computed here). */
void syren_packet(uint8_t address, uint8_t command, uint8_t data);

/* Queue the packet that sets a driver to coil command c (-127..127; sign = direction). */
void syren_drive(uint8_t address, int8_t c);

/* Bytes queued and not yet started on the wire (the one being shifted out is not counted). */
uint8_t syren_queued(void);

/* 1 when nothing is queued and the last stop bit has ended. */
uint8_t syren_idle(void);

#endif
