# The controller image for the emulated ARM MPS2 AN385 board (qemu-system-arm -M mps2-an385): the firmware's
# logic, the SIL's plant (host/sim) in place of the robot, and the board port (host/mps2). Included by
# host/due/CMakeLists.txt, so it is built by the same cross toolchain file and flags as the DUE image:
#   cmake --build firmware/build/due --target linarm_mps2.elf
set(MPS2_DIR "${HOST_DIR}/mps2")
add_executable(linarm_mps2.elf
  ${MPS2_DIR}/board_main.cpp ${MPS2_DIR}/mps2_board.cpp ${MPS2_DIR}/core_mps2.cpp ${MPS2_DIR}/startup_mps2.c
  ${HOST_DIR}/sim/sim_plant.cpp
  ${FW_SRC}/vsa.cpp ${FW_SRC}/trajectory.cpp ${FW_SRC}/safety_limits.cpp ${FW_SRC}/linarm.cpp
  ${FW_SRC}/command_reader.cpp ${FW_SRC}/linarm_app.cpp
  ${HOST_DIR}/cmdmessenger/CmdMessenger.cpp ${HOST_DIR}/stubs/print.cpp)
target_include_directories(linarm_mps2.elf PRIVATE ${MPS2_DIR} ${HOST_DIR}/sim ${FW_SRC} ${HOST_DIR}/stubs
  ${HOST_DIR}/cmdmessenger)
target_compile_options(linarm_mps2.elf PRIVATE -funsigned-char)
target_link_options(linarm_mps2.elf PRIVATE ${CPU} -nostartfiles --specs=nano.specs --specs=nosys.specs
  -T${MPS2_DIR}/mps2_an385.ld -Wl,--gc-sections -Wl,-Map=${CMAKE_BINARY_DIR}/linarm_mps2.map)
set_target_properties(linarm_mps2.elf PROPERTIES LINKER_LANGUAGE C)
target_link_libraries(linarm_mps2.elf PRIVATE m)
