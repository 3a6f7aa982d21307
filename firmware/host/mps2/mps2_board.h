// The ARM MPS2 AN385 board (Cortex-M3) as qemu-system-arm -M mps2-an385 models it: SysTick at 1 kHz from the
// 25 MHz system clock, and the CMSDK APB UARTs with interrupt-driven receive into ring buffers.
#ifndef LINARM_MPS2_BOARD_H
#define LINARM_MPS2_BOARD_H

#include <Arduino.h>
#include <stdint.h>

namespace mps2 {

const uint32_t SYSCLK_HZ = 25000000u;                   // qemu's mps2.c SYSCLK_FRQ
const uint32_t SYSTICK_COUNTS_PER_MS = SYSCLK_HZ / 1000u;  // one control period in SysTick counts

struct CmsdkUartRegs {
  volatile uint32_t data, state, ctrl, intstatus, bauddiv;
};

// A CMSDK UART as an Arduino Stream: receive by interrupt into a ring buffer, transmit by polling the
// holding register. The counters are what the board console reports.
class UartStream : public Stream {
 public:
  static const uint32_t RING = 256;  // bytes; a power of two
  explicit UartStream(uintptr_t base) : regs_(reinterpret_cast<CmsdkUartRegs*>(base)) {}
  void begin(uint32_t baud);
  void onRxInterrupt();  // from the UART's RX IRQ
  int available() override;
  int read() override;
  int peek() override;
  size_t write(uint8_t c) override;
  using Print::write;
  uint32_t rxBytes() const { return rxBytes_; }
  uint32_t rxOverruns() const { return rxOverruns_; }  // the UART's own RX overrun flag (a byte lost in hardware)
  uint32_t rxDropped() const { return rxDropped_; }    // bytes lost because the ring was full
  uint32_t txBytes() const { return txBytes_; }
  uint32_t rxHighWater() const { return rxHighWater_; }  // most bytes ever waiting in the ring
  void clearCounters() { rxOverruns_ = rxDropped_ = 0; rxHighWater_ = 0; }

 private:
  CmsdkUartRegs* regs_;
  uint8_t ring_[RING];
  volatile uint32_t head_ = 0, tail_ = 0;  // head written by the ISR, tail by the main loop
  volatile uint32_t rxBytes_ = 0, rxOverruns_ = 0, rxDropped_ = 0, rxHighWater_ = 0;
  uint32_t txBytes_ = 0;
};

extern UartStream uart0;  // the link to the host (the LINarm protocol)
extern UartStream uart1;  // the board console (status, and the lockstep harness of the tests)

void init();
uint32_t millis();
// A free-running count of system clock periods (25 MHz, as SysTick's), for measuring work: wraps every 171 s.
uint32_t counts();
inline void waitForInterrupt() { __asm volatile("wfi"); }
inline void disableIrq() { __asm volatile("cpsid i" ::: "memory"); }
inline void enableIrq() { __asm volatile("cpsie i" ::: "memory"); }

}  // namespace mps2

extern "C" uint32_t stack_high_water_bytes(void);
extern "C" uint32_t stack_size_bytes(void);

#endif  // LINARM_MPS2_BOARD_H
