// The sketch as the Arduino core runs it: setup() once, then loop() forever.
#include "linarm_controller.ino"

int main() {
  setup();
  for (;;) loop();
}
