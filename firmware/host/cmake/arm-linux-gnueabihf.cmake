# Cross build of firmware/host for 32-bit ARM Linux, run under qemu-arm: the DUE's ABI on a PC
# (ILP32: 32-bit int/long/pointers; plain char is unsigned; little-endian). Debian packages:
# g++-arm-linux-gnueabihf and qemu-user.
#   cmake -S firmware/host -B firmware/build/arm -DCMAKE_TOOLCHAIN_FILE=firmware/host/cmake/arm-linux-gnueabihf.cmake
set(CMAKE_SYSTEM_NAME Linux)
set(CMAKE_SYSTEM_PROCESSOR arm)
set(CMAKE_CXX_COMPILER arm-linux-gnueabihf-g++)
# Static executables: qemu-arm runs them without an ARM sysroot.
set(CMAKE_EXE_LINKER_FLAGS_INIT "-static")
set(CMAKE_CROSSCOMPILING_EMULATOR qemu-arm)
set(CMAKE_FIND_ROOT_PATH_MODE_PROGRAM NEVER)
set(CMAKE_FIND_ROOT_PATH_MODE_LIBRARY ONLY)
set(CMAKE_FIND_ROOT_PATH_MODE_INCLUDE ONLY)
