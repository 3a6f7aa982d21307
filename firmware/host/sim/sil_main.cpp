// Software-in-the-loop LINarm controller: the firmware's logic on a simulated robot, speaking the wire
// protocol on stdin/stdout (give it a pty master to look like a serial port).
//
//   linarm_sil [--centre M] [--delta M] [--start-homed] [--service]   real time, raw protocol bytes
//   linarm_sil --lockstep [...]                                    simulated time, driven line by line:
//       "S <hex>"  host bytes arrive now      -> "R <hex>" (what the firmware wrote)
//       "A <n>"    run n control ticks (1 ms) -> "R <hex>"
//       "F <N>"    a constant push on the handle (N, + towards +x) -> "R <hex>"
//       "N"        a fresh controller and robot, as after a restart (boot IDENTIFY) -> "R <hex>"
//       "Q"        quit
// --service: booted with the service jumper fitted (docs/linarm-protocol.md, "Safety envelope").
#include <errno.h>
#include <fcntl.h>
#include <poll.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <unistd.h>

#include <iostream>
#include <memory>
#include <string>

#include "rig.h"

namespace {

std::string toHex(const std::string& s) {
  static const char* digits = "0123456789abcdef";
  std::string out;
  out.reserve(s.size() * 2);
  for (unsigned char c : s) {
    out.push_back(digits[c >> 4]);
    out.push_back(digits[c & 15]);
  }
  return out;
}

std::string fromHex(const std::string& hex) {
  std::string out;
  for (size_t i = 0; i + 1 < hex.size(); i += 2) out.push_back(static_cast<char>(strtol(hex.substr(i, 2).c_str(), 0, 16)));
  return out;
}

bool writeAll(int fd, const std::string& data) {
  size_t off = 0;
  while (off < data.size()) {
    ssize_t n = write(fd, data.data() + off, data.size() - off);
    if (n < 0) {
      if (errno == EINTR) continue;
      if (errno == EAGAIN) {
        struct pollfd p = {fd, POLLOUT, 0};
        poll(&p, 1, 10);
        continue;
      }
      return false;
    }
    off += static_cast<size_t>(n);
  }
  return true;
}

int lockstep(const RigOptions& options) {
  std::unique_ptr<Rig> rig(new Rig(options));
  std::string line;
  while (std::getline(std::cin, line)) {
    if (line.empty()) continue;
    std::string out;
    if (line[0] == 'S') {
      out = rig->send(fromHex(line.size() > 2 ? line.substr(2) : ""));
    } else if (line[0] == 'A') {
      out = rig->advance(strtoul(line.c_str() + 1, 0, 10));
    } else if (line[0] == 'F') {
      rig->plant.externalForce = atof(line.c_str() + 1);
      out = rig->stream.take();
    } else if (line[0] == 'N') {
      rig.reset();
      rig.reset(new Rig(options));
      out = rig->stream.take();
    } else if (line[0] == 'Q') {
      return 0;
    } else {
      std::cerr << "linarm_sil: unknown lockstep line: " << line << "\n";
      return 2;
    }
    std::cout << "R " << toHex(out) << "\n" << std::flush;
  }
  return 0;
}

uint64_t nowUs() {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return static_cast<uint64_t>(ts.tv_sec) * 1000000u + static_cast<uint64_t>(ts.tv_nsec) / 1000u;
}

int realtime(Rig& rig) {
  const int in = STDIN_FILENO, out = STDOUT_FILENO;
  fcntl(in, F_SETFL, fcntl(in, F_GETFL) | O_NONBLOCK);
  if (!writeAll(out, rig.stream.take())) return 1;  // the boot IDENTIFY
  uint64_t next = nowUs() + 1000;
  char buf[512];
  for (;;) {
    uint64_t now = nowUs();
    int timeoutMs = next > now ? static_cast<int>((next - now + 999) / 1000) : 0;
    struct pollfd p = {in, POLLIN, 0};
    int r = poll(&p, 1, timeoutMs);
    if (r > 0) {
      ssize_t n = read(in, buf, sizeof buf);
      if (n == 0) return 0;  // EOF: the host went away
      if (n < 0 && errno != EAGAIN && errno != EINTR) return 0;  // EIO: pty slave closed
      if (n > 0 && !writeAll(out, rig.send(std::string(buf, static_cast<size_t>(n))))) return 1;
    } else if (r == 0 || (p.revents & (POLLHUP | POLLERR))) {
      if (p.revents & POLLHUP) usleep(1000);
    }
    now = nowUs();
    unsigned ticks = 0;
    while (now >= next) {
      rig.tick();
      next += 1000;
      if (++ticks >= 50) {  // far behind (the machine was busy): drop the backlog
        next = now + 1000;
        break;
      }
    }
    if (ticks && !writeAll(out, rig.stream.take())) return 1;
  }
}

}  // namespace

int main(int argc, char** argv) {
  signal(SIGPIPE, SIG_IGN);
  RigOptions o;
  bool step = false;
  for (int i = 1; i < argc; ++i) {
    std::string a = argv[i];
    if (a == "--lockstep") step = true;
    else if (a == "--start-homed") o.startHomed = true;
    else if (a == "--service") o.serviceMode = true;
    else if (a == "--centre" && i + 1 < argc) o.centre = atof(argv[++i]);
    else if (a == "--delta" && i + 1 < argc) o.delta = atof(argv[++i]);
    else {
      std::cerr << "usage: linarm_sil [--lockstep] [--centre M] [--delta M] [--start-homed] [--service]\n";
      return 2;
    }
  }
  if (step) return lockstep(o);
  Rig rig(o);
  return realtime(rig);
}
