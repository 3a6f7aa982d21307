/* Reset and vector table of the MPS2 AN385 image: paint the stack, copy .data, clear .bss, run the C++ static
 * constructors, call main(). IRQ 0 is UART0's receive interrupt (qemu's mps2.c wiring of the AN385). */
#include <stdint.h>

#define STACK_PAINT 0xC0DEFEEDu

extern uint32_t _sidata, _sdata, _edata, _sbss, _ebss, _estack, _stack_bottom;
extern int main(void);
extern void __libc_init_array(void);
void SysTick_Handler(void);
void Uart0Rx_IRQHandler(void);
void Uart1Rx_IRQHandler(void);

__attribute__((naked, noreturn)) void Reset_Handler(void) {
  /* Paint the whole stack area (nothing is on the stack yet: this function is naked and uses r0..r2). */
  __asm volatile(
      "ldr r0, =_stack_bottom\n"
      "ldr r1, =_estack\n"
      "ldr r2, =0xC0DEFEED\n"
      "1: cmp r0, r1\n"
      "bhs 2f\n"
      "str r2, [r0], #4\n"
      "b 1b\n"
      "2: b reset_c\n");
}

__attribute__((used, noreturn)) void reset_c(void) {
  uint32_t* src = &_sidata;
  for (uint32_t* dst = &_sdata; dst < &_edata;) *dst++ = *src++;
  for (uint32_t* dst = &_sbss; dst < &_ebss;) *dst++ = 0;
  __libc_init_array();
  main();
  for (;;) {
  }
}

/* The deepest the stack has been since reset: bytes from the top down to the lowest overwritten word. */
uint32_t stack_high_water_bytes(void) {
  const uint32_t* p = &_stack_bottom;
  while (p < &_estack && *p == STACK_PAINT) ++p;
  return (uint32_t)((const char*)&_estack - (const char*)p);
}

uint32_t stack_size_bytes(void) { return (uint32_t)((const char*)&_estack - (const char*)&_stack_bottom); }

static void Default_Handler(void) {
  for (;;) {
  }
}

__attribute__((section(".isr_vector"), used)) void (*const g_vectors[16 + 32])(void) = {
    (void (*)(void))(&_estack), Reset_Handler, Default_Handler, Default_Handler, Default_Handler,
    Default_Handler, Default_Handler, 0, 0, 0, 0, Default_Handler, Default_Handler, 0, Default_Handler,
    SysTick_Handler,
    Uart0Rx_IRQHandler, Default_Handler, Uart1Rx_IRQHandler, /* IRQ 0 / 2: UART0 / UART1 RX */
};

void* __dso_handle = 0;
void _init(void) {}
void _fini(void) {}
