#include "mps2_board.h"

namespace mps2 {

namespace {
// CMSDK APB UART register bits
const uint32_t STATE_TX_FULL = 1u << 0, STATE_RX_FULL = 1u << 1, STATE_RX_OVERRUN = 1u << 3;
const uint32_t CTRL_TX_EN = 1u << 0, CTRL_RX_EN = 1u << 1, CTRL_RX_INT_EN = 1u << 3;
const uint32_t INT_RX = 1u << 1;
// Cortex-M3 system registers
volatile uint32_t* const SYST_CSR = reinterpret_cast<volatile uint32_t*>(0xE000E010);
volatile uint32_t* const SYST_RVR = reinterpret_cast<volatile uint32_t*>(0xE000E014);
volatile uint32_t* const SYST_CVR = reinterpret_cast<volatile uint32_t*>(0xE000E018);
volatile uint32_t* const NVIC_ISER0 = reinterpret_cast<volatile uint32_t*>(0xE000E100);
const uint32_t IRQ_UART0_RX = 0, IRQ_UART1_RX = 2;  // AN385 wiring in qemu's mps2.c

volatile uint32_t g_ms = 0;
}  // namespace

UartStream uart0(0x40004000);
UartStream uart1(0x40005000);

void UartStream::begin(uint32_t baud) {
  regs_->bauddiv = SYSCLK_HZ / baud;  // >= 16 as the CMSDK UART requires
  regs_->ctrl = CTRL_TX_EN | CTRL_RX_EN | CTRL_RX_INT_EN;
}

void UartStream::onRxInterrupt() {
  // Acknowledge first, then drain: a byte that lands after the last RX_FULL check raises the interrupt again.
  // (Acknowledging after the drain lost it: RX_FULL stayed set with no interrupt pending, and the UART, which
  // has a single holding register, refused every later byte: the link stalled.)
  regs_->intstatus = INT_RX;  // INTCLEAR
  uint32_t state = regs_->state;
  if (state & STATE_RX_OVERRUN) {
    ++rxOverruns_;
    regs_->state = STATE_RX_OVERRUN;  // write-one-to-clear
  }
  while (regs_->state & STATE_RX_FULL) {
    uint8_t c = static_cast<uint8_t>(regs_->data);
    ++rxBytes_;
    uint32_t used = head_ - tail_;
    if (used >= RING) {
      ++rxDropped_;
      continue;
    }
    ring_[head_ & (RING - 1)] = c;
    head_ = head_ + 1;
    if (used + 1 > rxHighWater_) rxHighWater_ = used + 1;
  }
}

int UartStream::available() { return static_cast<int>(head_ - tail_); }

int UartStream::read() {
  if (head_ == tail_) return -1;
  int c = ring_[tail_ & (RING - 1)];
  tail_ = tail_ + 1;
  return c;
}

int UartStream::peek() { return head_ == tail_ ? -1 : ring_[tail_ & (RING - 1)]; }

size_t UartStream::write(uint8_t c) {
  while (regs_->state & STATE_TX_FULL) {
  }
  regs_->data = c;
  ++txBytes_;
  return 1;
}

void init() {
  uart0.begin(115200);
  uart1.begin(115200);
  *SYST_RVR = SYSTICK_COUNTS_PER_MS - 1;
  *SYST_CVR = 0;
  *SYST_CSR = 7;  // processor clock, interrupt, enable
  *NVIC_ISER0 = (1u << IRQ_UART0_RX) | (1u << IRQ_UART1_RX);
}

uint32_t millis() { return g_ms; }

uint32_t counts() {
  static uint32_t last = 0;
  for (;;) {
    uint32_t ms = g_ms;
    uint32_t val = *SYST_CVR;
    if (g_ms != ms) continue;  // a SysTick interrupt between the two reads: ms and val may not belong together
    uint32_t now = ms * SYSTICK_COUNTS_PER_MS + (SYSTICK_COUNTS_PER_MS - 1 - val);
    // Under qemu -icount the counter can read as reloaded before its interrupt has counted the millisecond:
    // time never runs backwards, so that reading is one period later than it looks.
    if (static_cast<int32_t>(now - last) < 0 && static_cast<int32_t>(now - last) > -static_cast<int32_t>(SYSTICK_COUNTS_PER_MS))
      now += SYSTICK_COUNTS_PER_MS;
    last = now;
    return now;
  }
}

}  // namespace mps2

extern "C" void SysTick_Handler(void) { mps2::g_ms = mps2::g_ms + 1; }
extern "C" void Uart0Rx_IRQHandler(void) { mps2::uart0.onRxInterrupt(); }
extern "C" void Uart1Rx_IRQHandler(void) { mps2::uart1.onRxInterrupt(); }
