/* simboard: runs the pivla arm firmware ELF on a simulated ATmega328P (16 MHz) with simavr.
 *
 * UART0 is exposed as a pseudo-terminal. The harness watches the servo pins (D2..D8) and measures each
 * pulse from its rising to its falling edge in simulated CPU cycles.
 *
 * stdout protocol (line buffered; simavr's own chatter goes to stderr):
 *   line 1:            the pty path the host opens (e.g. /dev/pts/7)
 *   "P <t_us> w0..w6"  measured pulse widths in microseconds at simulated time t_us, printed when any
 *                      width changed by >= 1 us since the last line, and at least every 500 ms
 *   "X <reason>"       the simulated CPU stopped (crash); the harness then exits with status 1
 *
 * usage: simboard [-r REALTIME_FACTOR] FIRMWARE.elf   (factor 1.0 = real time, 0 = as fast as possible)
 */
#define _GNU_SOURCE
#include <errno.h>
#include <math.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/prctl.h>
#include <time.h>
#include <unistd.h>

#include <simavr/avr_ioport.h>
#include <simavr/sim_avr.h>
#include <simavr/sim_elf.h>
#include <simavr/sim_irq.h>
#include <simavr/parts/uart_pty.h>

#define N_CHANNELS 7
#define F_CPU 16000000ULL

typedef struct {
  char port;
  int bit;
} pin_t;

/* Uno D2..D7 are PD2..PD7, D8 is PB0. */
static const pin_t kPins[N_CHANNELS] = {{'D', 2}, {'D', 3}, {'D', 4}, {'D', 5}, {'D', 6}, {'D', 7}, {'B', 0}};

static avr_t *avr;
static uart_pty_t uart;
static FILE *out;
static avr_cycle_count_t rise_cycle[N_CHANNELS];
static double width_us[N_CHANNELS];
static double printed_us[N_CHANNELS];
static avr_cycle_count_t last_print_cycle;

static void report(void) {
  int changed = avr->cycle - last_print_cycle >= F_CPU / 2;
  for (int i = 0; i < N_CHANNELS; i++) changed |= fabs(width_us[i] - printed_us[i]) >= 1.0;
  if (!changed) return;
  fprintf(out, "P %llu", (unsigned long long)(avr->cycle * 1000000ULL / F_CPU));
  for (int i = 0; i < N_CHANNELS; i++) {
    fprintf(out, " %.1f", width_us[i]);
    printed_us[i] = width_us[i];
  }
  fputc('\n', out);
  last_print_cycle = avr->cycle;
}

static void pin_changed(struct avr_irq_t *irq, uint32_t value, void *param) {
  (void)irq;
  int ch = (int)(intptr_t)param;
  if (value) {
    rise_cycle[ch] = avr->cycle;
  } else if (rise_cycle[ch]) {
    width_us[ch] = (double)(avr->cycle - rise_cycle[ch]) * 1e6 / (double)F_CPU;
    rise_cycle[ch] = 0;
    if (ch == N_CHANNELS - 1) report();
  }
}

static void on_signal(int sig) {
  (void)sig;
  /* uart_pty_stop() can block in pthread_join: leave without tearing the thread down. */
  _exit(0);
}

static double wall_seconds(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (double)ts.tv_sec + ts.tv_nsec * 1e-9;
}

int main(int argc, char **argv) {
  double factor = 1.0;
  int opt;
  while ((opt = getopt(argc, argv, "r:")) != -1) {
    if (opt == 'r') {
      factor = atof(optarg);
    } else {
      fprintf(stderr, "usage: %s [-r REALTIME_FACTOR] FIRMWARE.elf\n", argv[0]);
      return 2;
    }
  }
  if (optind != argc - 1) {
    fprintf(stderr, "usage: %s [-r REALTIME_FACTOR] FIRMWARE.elf\n", argv[0]);
    return 2;
  }
  const char *path = argv[optind];
  if (access(path, R_OK) != 0) {
    fprintf(stderr, "simboard: cannot read firmware %s: %s\n", path, strerror(errno));
    return 2;
  }
  /* Our protocol owns stdout; simavr prints to stdout too, so send fd 1 to stderr. */
  out = fdopen(dup(STDOUT_FILENO), "w");
  dup2(STDERR_FILENO, STDOUT_FILENO);
  setvbuf(out, NULL, _IOLBF, 0);
  prctl(PR_SET_PDEATHSIG, SIGTERM);
  signal(SIGINT, on_signal);
  signal(SIGTERM, on_signal);
  signal(SIGHUP, on_signal);

  elf_firmware_t fw;
  memset(&fw, 0, sizeof(fw));
  if (elf_read_firmware(path, &fw) != 0) {
    fprintf(stderr, "simboard: %s is not a readable AVR ELF\n", path);
    return 2;
  }
  avr = avr_make_mcu_by_name("atmega328p");
  if (!avr) {
    fprintf(stderr, "simboard: simavr has no atmega328p core\n");
    return 2;
  }
  avr_init(avr);
  avr_load_firmware(avr, &fw);
  avr->frequency = F_CPU;

  for (int i = 0; i < N_CHANNELS; i++) {
    avr_irq_t *irq = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ(kPins[i].port), kPins[i].bit);
    avr_irq_register_notify(irq, pin_changed, (void *)(intptr_t)i);
  }
  uart_pty_init(avr, &uart);
  uart_pty_connect(&uart, '0');
  fprintf(out, "%s\n", uart.port[0].slavename);

  double start = wall_seconds();
  avr_cycle_count_t next_sync = 0;
  for (;;) {
    int state = avr_run(avr);
    if (state == cpu_Done || state == cpu_Crashed) {
      fprintf(out, "X %s\n", state == cpu_Crashed ? "crashed" : "stopped");
      fflush(out);
      _exit(1);
    }
    if (factor > 0 && avr->cycle >= next_sync) {
      next_sync = avr->cycle + F_CPU / 1000;
      double ahead = (double)avr->cycle / (double)F_CPU / factor - (wall_seconds() - start);
      if (ahead > 0.001) {
        struct timespec ts = {0, (long)(ahead * 1e9)};
        nanosleep(&ts, NULL);
      }
    }
  }
}
