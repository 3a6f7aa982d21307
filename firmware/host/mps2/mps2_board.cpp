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

// CMSDK APB timer 1, free running from 0xFFFFFFFF at the 25 MHz PCLK: the work counter. Not SysTick: under
// qemu -icount, SysTick's counter could read as reloaded before its interrupt had counted the millisecond,
// and a (milliseconds, SysTick value) pair then came out one period short.
volatile uint32_t* const TIMER1_CTRL = reinterpret_cast<volatile uint32_t*>(0x40001000);
volatile uint32_t* const TIMER1_VALUE = reinterpret_cast<volatile uint32_t*>(0x40001004);
volatile uint32_t* const TIMER1_RELOAD = reinterpret_cast<volatile uint32_t*>(0x40001008);

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
  *TIMER1_RELOAD = 0xFFFFFFFFu;
  *TIMER1_VALUE = 0xFFFFFFFFu;
  *TIMER1_CTRL = 1;  // enable, no interrupt
  *NVIC_ISER0 = (1u << IRQ_UART0_RX) | (1u << IRQ_UART1_RX);
}

uint32_t millis() { return g_ms; }

uint32_t counts() { return 0xFFFFFFFFu - *TIMER1_VALUE; }  // counts up at 25 MHz

}  // namespace mps2

extern "C" void SysTick_Handler(void) { mps2::g_ms = mps2::g_ms + 1; }
extern "C" void Uart0Rx_IRQHandler(void) { mps2::uart0.onRxInterrupt(); }
extern "C" void Uart1Rx_IRQHandler(void) { mps2::uart1.onRxInterrupt(); }
