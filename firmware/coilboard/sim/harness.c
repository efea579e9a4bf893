/* simavr harness for the coil-board firmware: the real ELF on a simulated ATmega328P, in real time.
 *
 *   harness [--watch-stdin] FIRMWARE.elf
 *
 * - USART0 is bridged to a pty (what the host driver opens, as it would open /dev/ttyACM0).
 * - The SyRen bus pin PD3 is watched through simavr's pin-change IRQ; each edge is stamped with the
 *   simulated cycle, and a 9600 8N1 decoder turns the waveform back into bytes (sampled in the
 *   middle of each bit, stop bit checked) that are written to a second pty.
 * - Pacing: simulated time is tied to CLOCK_MONOTONIC. The core runs in slices of SLICE_US of
 *   simulated time; when it is ahead of the wall clock the harness waits in ppoll() on the pty
 *   until the wall clock catches up (a host byte ends the wait at once). The firmware sleeps
 *   between interrupts, and simavr jumps a sleeping core to its next timer event, so an idle board
 *   costs little. If the host machine is too slow and the core falls more than MAX_LAG_US behind,
 *   the harness lets the missing time go (counted as a slip) rather than burst to catch up.
 * - On start it prints exactly one line to stdout, `READY uart=/dev/pts/N syren=/dev/pts/M`, and
 *   flushes; everything else (simavr's own messages, statistics) goes to stderr.
 * - SIGTERM or SIGINT: clean exit (status 0). With --watch-stdin it also exits when its stdin
 *   reaches end of file, so a launcher that dies cannot leave it running.
 */
#define _GNU_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <poll.h>
#include <signal.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include "avr_ioport.h"
#include "avr_uart.h"
#include "sim_avr.h"
#include "sim_elf.h"
#include "sim_irq.h"

#define DEFAULT_MCU "atmega328p"
#define DEFAULT_FREQUENCY 16000000u
#define SYREN_BAUD 9600.0
#define SYREN_PORT 'D'
#define SYREN_PIN 3
#define DDRD_ADDRESS 0x2A /* data-space address of DDRD on the ATmega328P */
#define SLICE_US 200
#define MAX_LAG_US 20000
#define HOST_BUFFER 4096

static volatile sig_atomic_t stop_requested;

static void on_signal(int sig)
{
	(void)sig;
	stop_requested = 1;
}

struct pty {
	int master;
	int slave; /* kept open so the pty survives a client closing it, like a plugged-in board */
	char path[64];
};

static int open_pty(struct pty *p)
{
	struct termios tio;
	p->master = posix_openpt(O_RDWR | O_NOCTTY);
	if (p->master < 0 || grantpt(p->master) < 0 || unlockpt(p->master) < 0 ||
	    ptsname_r(p->master, p->path, sizeof p->path) != 0)
		return -1;
	p->slave = open(p->path, O_RDWR | O_NOCTTY);
	if (p->slave < 0 || tcgetattr(p->slave, &tio) < 0)
		return -1;
	cfmakeraw(&tio); /* bytes, not lines: no echo, no CR/LF translation */
	if (tcsetattr(p->slave, TCSANOW, &tio) < 0)
		return -1;
	return fcntl(p->master, F_SETFL, fcntl(p->master, F_GETFL) | O_NONBLOCK);
}

static struct stats {
	uint64_t host_in, host_out, host_dropped;
	uint64_t syren_bytes, syren_framing_errors, syren_dropped;
	uint64_t slips, slipped_us;
	uint64_t resets, cycles_before_reset;
} stats;

/* ---- host link: USART0 <-> pty ---------------------------------------------------------------- */

static struct host_link {
	avr_irq_t *irq; /* simavr's UART0 IRQs */
	struct pty pty;
	uint8_t in[HOST_BUFFER]; /* bytes read from the pty, not yet taken by the UART */
	size_t in_start, in_end;
	int xoff;                /* the UART's receive FIFO is full */
} host;

static void write_or_drop(int fd, const uint8_t *data, size_t n, uint64_t *dropped)
{
	while (n > 0) {
		ssize_t done = write(fd, data, n);
		if (done < 0) {
			if (errno == EINTR)
				continue;
			*dropped += n; /* nobody is reading and the pty is full: a wire would lose them too */
			return;
		}
		data += done;
		n -= (size_t)done;
	}
}

static void on_uart_output(struct avr_irq_t *irq, uint32_t value, void *param)
{
	(void)irq;
	(void)param;
	uint8_t byte = (uint8_t)value;
	stats.host_out++;
	write_or_drop(host.pty.master, &byte, 1, &stats.host_dropped);
}

static void feed_uart(void)
{
	while (!host.xoff && host.in_start < host.in_end) {
		avr_raise_irq(host.irq + UART_IRQ_INPUT, host.in[host.in_start++]);
		stats.host_in++;
	}
	if (host.in_start > 0) { /* keep the waiting bytes at the front: room to read more */
		memmove(host.in, host.in + host.in_start, host.in_end - host.in_start);
		host.in_end -= host.in_start;
		host.in_start = 0;
	}
}

static void on_uart_xon(struct avr_irq_t *irq, uint32_t value, void *param)
{
	(void)irq;
	(void)value;
	(void)param;
	host.xoff = 0;
	feed_uart();
}

static void on_uart_xoff(struct avr_irq_t *irq, uint32_t value, void *param)
{
	(void)irq;
	(void)param;
	host.xoff = value != 0;
}

static void read_host(void)
{
	if (host.in_end == sizeof host.in)
		return; /* the firmware is not taking bytes; leave the rest in the pty */
	ssize_t n = read(host.pty.master, host.in + host.in_end, sizeof host.in - host.in_end);
	if (n > 0)
		host.in_end += (size_t)n;
	feed_uart();
}

/* ---- SyRen bus: PD3 waveform -> bytes -> pty --------------------------------------------------- */

static struct syren_decoder {
	avr_t *avr;
	struct pty pty;
	double bit_cycles;
	int level;           /* line level now (1 = idle) */
	int receiving;       /* inside a character that began with a start bit at t0 */
	avr_cycle_count_t t0;
	int n_edges;
	avr_cycle_count_t edge_at[16];
	int edge_level[16];
} bus;

static int level_at(double t)
{
	int level = 0; /* the start bit */
	for (int i = 0; i < bus.n_edges && (double)bus.edge_at[i] <= t; i++)
		level = bus.edge_level[i];
	return level;
}

static void finish_character(void)
{
	uint8_t byte = 0;
	double t0 = (double)bus.t0;
	for (int i = 0; i < 8; i++)
		if (level_at(t0 + (1.5 + i) * bus.bit_cycles))
			byte |= (uint8_t)(1u << i);
	bus.receiving = 0;
	if (!level_at(t0 + 9.5 * bus.bit_cycles)) {
		stats.syren_framing_errors++;
		return;
	}
	stats.syren_bytes++;
	write_or_drop(bus.pty.master, &byte, 1, &stats.syren_dropped);
}

/* Called when the core is at `now`: completes a character whose stop bit has been sampled. */
static void syren_poll(avr_cycle_count_t now)
{
	if (bus.receiving && (double)now >= (double)bus.t0 + 9.5 * bus.bit_cycles)
		finish_character();
}

static void on_pin(struct avr_irq_t *irq, uint32_t value, void *param)
{
	(void)irq;
	(void)param;
	avr_t *avr = bus.avr;
	/* an input pin is not driving the line: the bus rests high (the drivers' inputs idle high) */
	int level = (avr->data[DDRD_ADDRESS] & (1u << SYREN_PIN)) ? (value != 0) : 1;
	if (level == bus.level)
		return;
	syren_poll(avr->cycle);
	bus.level = level;
	if (!bus.receiving) {
		if (level == 0) {
			bus.receiving = 1;
			bus.t0 = avr->cycle;
			bus.n_edges = 0;
		}
		return;
	}
	if (bus.n_edges < (int)(sizeof bus.edge_at / sizeof bus.edge_at[0])) {
		bus.edge_at[bus.n_edges] = avr->cycle;
		bus.edge_level[bus.n_edges] = level;
		bus.n_edges++;
	}
}

/* ---- main loop ---------------------------------------------------------------------------------- */

static int64_t monotonic_ns(void)
{
	struct timespec ts;
	clock_gettime(CLOCK_MONOTONIC, &ts);
	return (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
}

static void no_sleep(avr_t *avr, avr_cycle_count_t how_long)
{
	/* simavr would usleep() here; the harness paces against the wall clock itself */
	(void)avr;
	(void)how_long;
}

static void usage(const char *argv0)
{
	fprintf(stderr, "usage: %s [--watch-stdin] FIRMWARE.elf\n", argv0);
}

int main(int argc, char **argv)
{
	const char *elf_path = NULL;
	int watch_stdin = 0;
	for (int i = 1; i < argc; i++) {
		if (strcmp(argv[i], "--watch-stdin") == 0)
			watch_stdin = 1;
		else if (argv[i][0] == '-' || elf_path) {
			usage(argv[0]);
			return 2;
		} else
			elf_path = argv[i];
	}
	if (!elf_path) {
		usage(argv[0]);
		return 2;
	}

	/* stdout carries only the READY line: keep it aside, and send everything else to stderr */
	int ready_fd = dup(STDOUT_FILENO);
	if (ready_fd < 0 || dup2(STDERR_FILENO, STDOUT_FILENO) < 0) {
		perror("harness: stdout");
		return 1;
	}

	elf_firmware_t fw;
	memset(&fw, 0, sizeof fw);
	if (elf_read_firmware(elf_path, &fw) != 0) {
		fprintf(stderr, "harness: cannot read the firmware %s\n", elf_path);
		return 1;
	}
	if (!fw.mmcu[0])
		snprintf(fw.mmcu, sizeof fw.mmcu, "%s", DEFAULT_MCU);
	if (!fw.frequency)
		fw.frequency = DEFAULT_FREQUENCY;
	avr_t *avr = avr_make_mcu_by_name(fw.mmcu);
	if (!avr) {
		fprintf(stderr, "harness: simavr does not know the MCU %s\n", fw.mmcu);
		return 1;
	}
	avr_init(avr);
	avr->frequency = fw.frequency;
	avr->sleep = no_sleep;
	avr_load_firmware(avr, &fw);

	if (open_pty(&host.pty) < 0 || open_pty(&bus.pty) < 0) {
		perror("harness: pty");
		return 1;
	}

	uint32_t uart_flags = 0; /* no console echo of UART bytes, no usleep when polled */
	avr_ioctl(avr, AVR_IOCTL_UART_SET_FLAGS('0'), &uart_flags);
	host.irq = avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), 0);
	avr_irq_register_notify(host.irq + UART_IRQ_OUTPUT, on_uart_output, NULL);
	avr_irq_register_notify(host.irq + UART_IRQ_OUT_XON, on_uart_xon, NULL);
	avr_irq_register_notify(host.irq + UART_IRQ_OUT_XOFF, on_uart_xoff, NULL);

	bus.avr = avr;
	bus.level = 1;
	bus.bit_cycles = (double)avr->frequency / SYREN_BAUD;
	avr_irq_t *pin = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ(SYREN_PORT), SYREN_PIN);
	avr_irq_register_notify(pin, on_pin, NULL);

	struct sigaction sa;
	memset(&sa, 0, sizeof sa);
	sa.sa_handler = on_signal;
	sigaction(SIGTERM, &sa, NULL);
	sigaction(SIGINT, &sa, NULL);
	signal(SIGPIPE, SIG_IGN);

	dprintf(ready_fd, "READY uart=%s syren=%s\n", host.pty.path, bus.pty.path);
	close(ready_fd);

	const double cycles_per_ns = (double)avr->frequency / 1e9;
	int64_t start_ns = monotonic_ns();
	const int64_t run_start_ns = start_ns;
	avr_cycle_count_t start_cycle = avr->cycle;
	struct pollfd fds[2] = {
		{.fd = host.pty.master, .events = POLLIN},
		{.fd = STDIN_FILENO, .events = POLLIN},
	};
	int nfds = watch_stdin ? 2 : 1;
	int exit_status = 0;

	avr_cycle_count_t previous_cycle = avr->cycle;
	while (!stop_requested) {
		if (avr->cycle < previous_cycle) {
			/* a reset (the AVR watchdog) restarted the cycle count: pace from here */
			stats.resets++;
			stats.cycles_before_reset += previous_cycle - start_cycle;
			start_cycle = avr->cycle;
			start_ns = monotonic_ns();
			bus.receiving = 0;
			fprintf(stderr, "harness: the AVR was reset\n");
		}
		previous_cycle = avr->cycle;
		int64_t wall_ns = monotonic_ns() - start_ns;
		int64_t sim_ns = (int64_t)((double)(avr->cycle - start_cycle) / cycles_per_ns);
		if (wall_ns - sim_ns > (int64_t)MAX_LAG_US * 1000) {
			int64_t slip = wall_ns - sim_ns - (int64_t)MAX_LAG_US * 1000;
			start_ns += slip;
			wall_ns -= slip;
			stats.slips++;
			stats.slipped_us += (uint64_t)(slip / 1000);
		}
		if (sim_ns <= wall_ns) {
			avr_cycle_count_t target = start_cycle +
				(avr_cycle_count_t)((double)(wall_ns + SLICE_US * 1000) * cycles_per_ns);
			while (avr->cycle < target) {
				int state = avr_run(avr);
				if (state == cpu_Done || state == cpu_Crashed) {
					fprintf(stderr, "harness: the firmware stopped (%s) at cycle %llu\n",
					        state == cpu_Done ? "done" : "crashed",
					        (unsigned long long)avr->cycle);
					exit_status = 1;
					stop_requested = 1;
					break;
				}
				syren_poll(avr->cycle);
			}
			sim_ns = (int64_t)((double)(avr->cycle - start_cycle) / cycles_per_ns);
		}
		int64_t ahead_ns = sim_ns - (monotonic_ns() - start_ns);
		struct timespec wait = {0, 0};
		if (ahead_ns > 0) {
			wait.tv_sec = ahead_ns / 1000000000;
			wait.tv_nsec = ahead_ns % 1000000000;
		}
		/* a full input buffer means the firmware is not keeping up: leave the bytes in the pty */
		fds[0].events = host.in_end < sizeof host.in ? POLLIN : 0;
		int ready = ppoll(fds, (nfds_t)nfds, &wait, NULL);
		if (ready < 0 && errno != EINTR) {
			perror("harness: ppoll");
			exit_status = 1;
			break;
		}
		if (ready > 0 && (fds[0].revents & POLLIN))
			read_host();
		if (ready > 0 && nfds == 2 && (fds[1].revents & (POLLIN | POLLHUP))) {
			char sink[64];
			if (read(STDIN_FILENO, sink, sizeof sink) <= 0)
				stop_requested = 1; /* the launcher is gone */
		}
		feed_uart();
	}

	double sim_s = (double)(stats.cycles_before_reset + avr->cycle - start_cycle) / (double)avr->frequency;
	double wall_s = (double)(monotonic_ns() - run_start_ns) / 1e9;
	fprintf(stderr,
	        "harness: stopped after %.3f s simulated in %.3f s; host bytes in %llu out %llu dropped %llu; "
	        "syren bytes %llu framing errors %llu dropped %llu; pacing slips %llu (%llu us); resets %llu\n",
	        sim_s, wall_s, (unsigned long long)stats.host_in, (unsigned long long)stats.host_out,
	        (unsigned long long)stats.host_dropped, (unsigned long long)stats.syren_bytes,
	        (unsigned long long)stats.syren_framing_errors,
	        (unsigned long long)stats.syren_dropped, (unsigned long long)stats.slips,
	        (unsigned long long)stats.slipped_us, (unsigned long long)stats.resets);
	avr_terminate(avr);
	return exit_status;
}
