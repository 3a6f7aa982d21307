// Compiles the DUE sketch (linarm_controller.ino) as C++ against the host's stub Arduino headers, and links
// it, so that syntax and type errors in the DUE-only files are caught by the host build. Never run.
#include "linarm_controller.ino"

int main() {
  setup();
  loop();
  return 0;
}
