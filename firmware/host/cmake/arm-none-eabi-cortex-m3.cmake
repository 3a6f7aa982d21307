# Bare-metal cross build for the Arduino DUE's CPU (SAM3X8E, Cortex-M3, Thumb-2, no FPU) with Debian's
# gcc-arm-none-eabi + libnewlib-arm-none-eabi (newlib-nano). Used by firmware/host/due (size report).
set(CMAKE_SYSTEM_NAME Generic)
set(CMAKE_SYSTEM_PROCESSOR cortex-m3)
set(CMAKE_C_COMPILER arm-none-eabi-gcc)
set(CMAKE_CXX_COMPILER arm-none-eabi-g++)
set(CMAKE_TRY_COMPILE_TARGET_TYPE STATIC_LIBRARY)  # no startup code for the compiler checks
set(CMAKE_FIND_ROOT_PATH_MODE_PROGRAM NEVER)
