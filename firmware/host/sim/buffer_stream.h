// An in-memory Arduino Stream: the host writes into `rx`, the firmware's output collects in `tx`.
#ifndef LINARM_BUFFER_STREAM_H
#define LINARM_BUFFER_STREAM_H

#include <Arduino.h>

#include <deque>
#include <string>

class BufferStream : public Stream {
 public:
  void feed(const std::string& bytes) { rx.insert(rx.end(), bytes.begin(), bytes.end()); }
  std::string take() {
    std::string out;
    out.swap(tx);
    return out;
  }
  int available() override { return static_cast<int>(rx.size()); }
  int read() override {
    if (rx.empty()) return -1;
    int c = static_cast<unsigned char>(rx.front());
    rx.pop_front();
    return c;
  }
  int peek() override { return rx.empty() ? -1 : static_cast<unsigned char>(rx.front()); }
  size_t write(uint8_t c) override {
    tx.push_back(static_cast<char>(c));
    return 1;
  }
  using Print::write;
  std::deque<char> rx;
  std::string tx;
};

#endif  // LINARM_BUFFER_STREAM_H
