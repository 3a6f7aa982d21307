// The LINarm controller image for the emulated MPS2 AN385 board: the same logic as the DUE sketch (Linarm,
// LinarmApp, CmdMessenger stand-in) behind the same Hal, with the SIL's plant (host/sim) running on the MCU in
// place of the motors, encoders and switches. The protocol runs on UART0; UART1 is the board console:
//
//   "STATUS"   -> "STATUS ticks=.. tick_max=.. tick_p99=.. plant_max=.. poll_max=.. late=.. stack_hwm=..
//                  stack_size=.. rx_bytes=.. rx_overruns=.. rx_dropped=.. rx_ring_hwm=.. counts_per_ms=25000"
//                 work in counts of the 25 MHz system clock (CMSDK timer 1): with qemu's -icount shift=N one count is 40 / 2^N
//                 instructions. tick = Linarm/LinarmApp's controlTick (the firmware's 1 kHz work), plant =
//                 the simulated robot's step (stands in for hardware, not part of the DUE's budget), poll =
//                 one app.poll() that had bytes to read.
//   "RESET"    -> "OK": clear the work statistics, the late-tick and the receive counters.
//   Lockstep (simulated time, as linarm_sil --lockstep, for the shared protocol scenarios); every reply is
//   "R <n>": n = the bytes written to UART0 since the previous reply, which the harness reads there:
//   "L <centre_um> <delta_um> <homed> <service>"  a fresh controller and robot, ticks only on "A" from now on
//   "S <n>"    the host has sent n bytes on UART0 since "L" (a running total: some may have arrived before this
//              line): receive and dispatch them all
//   "A <n>"    run n control ticks (1 ms of simulated time each)
//   "F <mN>"   a constant push on the handle (milli-newton, + towards +x)
//   "N"        power cycle (boot IDENTIFY)
//   "Z"        "R 0": forget the count (bytes written before the harness connected were dropped by qemu)
// Until the first console byte arrives the board says "HELLO mps2-1.0" there every 100 ms: a host must not
// send before the UARTs are enabled (qemu's CMSDK UART refuses bytes while RX is off, and its chardev may not
// look at the socket again), so harnesses wait for it.
#include <Arduino.h>
#include <CmdMessenger.h>
#include <stdlib.h>
#include <string.h>

#include "linarm.h"
#include "linarm_app.h"
#include "linarm_config.h"
#include "mps2_board.h"
#include "sim_hal.h"
#include "sim_plant.h"

inline void* operator new(size_t, void* where) noexcept { return where; }

namespace {

const char FIRMWARE_VERSION[] = "mps2-1.0";

struct Options {
  double centre = 0.20, delta = 0.02;
  bool startHomed = false, service = false;
};

// Controller and robot, rebuilt in place on a power cycle. The storage is zeroed before every construction:
// CmdMessenger 4.2.0's init() leaves startCommand as it finds it (firmware/README.md).
struct Machine {
  explicit Machine(const Options& o)
      : plant(PlantParams(), o.centre, o.delta), hal(plant, o.service), messenger(mps2::uart0), linarm(hal),
        app(messenger, mps2::uart0, linarm, hal, FIRMWARE_VERSION) {
    hal.begin();
    linarm.begin();
    if (o.startHomed) linarm.presetHomed(static_cast<float>(plant.x[0]), static_cast<float>(plant.x[1]),
                                         static_cast<float>(plant.h));
    app.begin();
  }
  SimPlant plant;
  SimHal hal;
  CmdMessenger messenger;
  Linarm linarm;
  LinarmApp app;
};

alignas(Machine) unsigned char g_storage[sizeof(Machine)];
Machine* g_machine = 0;
Options g_options;
bool g_lockstep = false;

Machine& build(const Options& o) {
  memset(g_storage, 0, sizeof g_storage);
  g_machine = new (g_storage) Machine(o);
  return *g_machine;
}

// ------------------------------------------------------------------------------------ work statistics
const uint32_t BUCKET_COUNTS = 4;  // histogram resolution: 4 counts (160 instructions at shift 0)
const uint32_t BUCKETS = 1024;
struct Stats {
  uint32_t ticks, tickMax, plantMax, pollMax, late;
  uint16_t histogram[BUCKETS];  // saturating; the last bucket holds everything longer
} g_stats;

void recordTick(uint32_t work) {
  ++g_stats.ticks;
  if (work > g_stats.tickMax) g_stats.tickMax = work;
  uint32_t b = work / BUCKET_COUNTS;
  if (b >= BUCKETS) b = BUCKETS - 1;
  if (g_stats.histogram[b] != 0xFFFF) ++g_stats.histogram[b];
}

uint32_t tickP99() {
  uint32_t total = 0;
  for (uint32_t b = 0; b < BUCKETS; ++b) total += g_stats.histogram[b];
  uint32_t need = total - total / 100, seen = 0;  // the smallest bucket below which 99 % of the ticks lie
  for (uint32_t b = 0; b < BUCKETS; ++b) {
    seen += g_stats.histogram[b];
    if (total && seen >= need) return (b + 1) * BUCKET_COUNTS;
  }
  return 0;
}

void tick(Machine& m) {
  uint32_t t0 = mps2::counts();
  m.app.controlTick();
  uint32_t t1 = mps2::counts();
  m.plant.step(0.001);  // as the SIL's Rig steps it
  m.hal.advanceMicros(cfg::LOOP_PERIOD_US);
  uint32_t t2 = mps2::counts();
  recordTick(t1 - t0);
  if (t2 - t1 > g_stats.plantMax) g_stats.plantMax = t2 - t1;
}

void poll(Machine& m) {
  uint32_t t0 = mps2::counts();
  m.app.poll();
  uint32_t work = mps2::counts() - t0;
  if (work > g_stats.pollMax) g_stats.pollMax = work;
}

// ------------------------------------------------------------------------------------ board console
void say(const char* s) { mps2::uart1.write(s); }
void sayNumber(const char* key, uint32_t v) {
  mps2::uart1.print(' ');
  mps2::uart1.print(key);
  mps2::uart1.print('=');
  mps2::uart1.print(static_cast<unsigned long>(v));
}

uint32_t g_txReported = 0;
uint32_t g_rxBase = 0;  // UART0 bytes received before the lockstep harness's "L"
void replyCount() {
  uint32_t tx = mps2::uart0.txBytes();
  say("R ");
  mps2::uart1.print(static_cast<unsigned long>(tx - g_txReported));
  say("\n");
  g_txReported = tx;
}

void status() {
  say("STATUS");
  sayNumber("ticks", g_stats.ticks);
  sayNumber("tick_max", g_stats.tickMax);
  sayNumber("tick_p99", tickP99() < g_stats.tickMax ? tickP99() : g_stats.tickMax);  // bucket edge, never above the worst
  sayNumber("plant_max", g_stats.plantMax);
  sayNumber("poll_max", g_stats.pollMax);
  sayNumber("late", g_stats.late);
  sayNumber("stack_hwm", stack_high_water_bytes());
  sayNumber("stack_size", stack_size_bytes());
  sayNumber("rx_bytes", mps2::uart0.rxBytes());
  sayNumber("rx_overruns", mps2::uart0.rxOverruns());
  sayNumber("rx_dropped", mps2::uart0.rxDropped());
  sayNumber("rx_ring_hwm", mps2::uart0.rxHighWater());
  sayNumber("counts_per_ms", mps2::SYSTICK_COUNTS_PER_MS);
  say(" lockstep=");
  say(g_lockstep ? "1" : "0");
  say("\n");
}

void command(char* line) {
  char* rest = line + 1;
  long a = strtol(rest, &rest, 10);
  Machine& m = *g_machine;
  if (strcmp(line, "STATUS") == 0) {
    status();
  } else if (strcmp(line, "RESET") == 0) {
    memset(&g_stats, 0, sizeof g_stats);
    mps2::uart0.clearCounters();
    say("OK\n");
  } else if (line[0] == 'L') {
    Options o;
    o.centre = a * 1e-6;
    o.delta = strtol(rest, &rest, 10) * 1e-6;
    o.startHomed = strtol(rest, &rest, 10) != 0;
    o.service = strtol(rest, &rest, 10) != 0;
    g_options = o;
    g_lockstep = true;
    g_rxBase = mps2::uart0.rxBytes();
    build(o);
    replyCount();
  } else if (line[0] == 'S') {
    uint32_t target = g_rxBase + static_cast<uint32_t>(a);
    while (static_cast<int32_t>(mps2::uart0.rxBytes() - target) < 0 || mps2::uart0.available() > 0) poll(m);
    replyCount();
  } else if (line[0] == 'A') {
    for (long i = 0; i < a; ++i) tick(m);
    replyCount();
  } else if (line[0] == 'F') {
    m.plant.externalForce = a * 1e-3;
    replyCount();
  } else if (line[0] == 'N') {
    build(g_options);
    replyCount();
  } else if (line[0] == 'Z') {  // bytes written before a harness connected were never seen by it
    g_txReported = mps2::uart0.txBytes();
    replyCount();
  } else {
    say("ERR\n");
  }
}

char g_line[48];
uint32_t g_lineLength = 0;
bool g_consoleHeard = false;
void console() {
  int c;
  if (!g_consoleHeard && mps2::millis() % 100 == 0) {
    static uint32_t lastHello = 0xFFFFFFFF;
    if (lastHello != mps2::millis()) {
      lastHello = mps2::millis();
      say("HELLO ");
      say(FIRMWARE_VERSION);
      say("\n");
    }
  }
  while ((c = mps2::uart1.read()) >= 0) {
    g_consoleHeard = true;
    if (c == '\n' || c == '\r') {
      if (g_lineLength) {
        g_line[g_lineLength] = 0;
        command(g_line);
      }
      g_lineLength = 0;
    } else if (g_lineLength < sizeof g_line - 1) {
      g_line[g_lineLength++] = static_cast<char>(c);
    }
  }
}

}  // namespace

int main() {
  mps2::init();
  build(g_options);
  uint32_t nextTick = mps2::millis() + 1;
  for (;;) {
    console();
    if (g_lockstep) {
      mps2::waitForInterrupt();  // the harness drives everything from the console
      continue;
    }
    Machine& m = *g_machine;
    if (mps2::uart0.available() > 0) poll(m);
    unsigned int ticks = 0;
    while (static_cast<int32_t>(mps2::millis() - nextTick) >= 0) {
      if (ticks == cfg::MAX_CATCH_UP_TICKS) {  // too far behind: drop the backlog, as the DUE sketch does
        nextTick = mps2::millis() + 1;
        ++g_stats.late;
        break;
      }
      if (ticks) ++g_stats.late;
      tick(m);
      ++nextTick;
      ++ticks;
    }
    mps2::disableIrq();  // sleep only when nothing arrived meanwhile; a pending interrupt still wakes the WFI
    if (mps2::uart0.available() == 0 && mps2::uart1.available() == 0 &&
        static_cast<int32_t>(mps2::millis() - nextTick) < 0)
      mps2::waitForInterrupt();
    mps2::enableIrq();
  }
}
