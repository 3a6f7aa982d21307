// The firmware on a simulated LINarm2, stepped in lockstep: used by the SIL executable and the unit tests.
#ifndef LINARM_RIG_H
#define LINARM_RIG_H

#include <CmdMessenger.h>
#include <string.h>

#include <new>
#include <string>

#include "buffer_stream.h"
#include "linarm.h"
#include "linarm_app.h"
#include "sim_hal.h"
#include "sim_plant.h"

// CmdMessenger 4.2.0's init() never sets startCommand: an instance on uninitialised memory may send its
// first frame without its id (",0;"). The sketch's instance is static, so zeroed before construction; a Rig
// can live on the stack, so its messenger is built in storage zeroed here (the stand-in, like 4.2.0, leaves
// startCommand to the memory it is given).
class ZeroedMessenger {
 public:
  explicit ZeroedMessenger(Stream& comms) {
    memset(storage_, 0, sizeof storage_);
    messenger_ = new (storage_) CmdMessenger(comms);
  }
  ~ZeroedMessenger() { messenger_->~CmdMessenger(); }
  CmdMessenger& get() { return *messenger_; }

 private:
  ZeroedMessenger(const ZeroedMessenger&);
  ZeroedMessenger& operator=(const ZeroedMessenger&);
  alignas(CmdMessenger) unsigned char storage_[sizeof(CmdMessenger)];
  CmdMessenger* messenger_;
};

struct RigOptions {
  double centre = 0.20;  // m, where the plant starts
  double delta = 0.02;   // m, pretension
  bool startHomed = false;
  bool serviceMode = false;  // as if booted with the service jumper fitted
  PlantParams params;
  const char* firmwareVersion = "sil-1.0";
};

class Rig {
 public:
  explicit Rig(const RigOptions& o = RigOptions())
      : plant(o.params, o.centre, o.delta), hal(plant, o.serviceMode), messengerStorage(stream),
        messenger(messengerStorage.get()), linarm(hal), app(messenger, stream, linarm, hal, o.firmwareVersion) {
    hal.begin();
    linarm.begin();
    if (o.startHomed) linarm.presetHomed(static_cast<float>(plant.x[0]), static_cast<float>(plant.x[1]),
                                         static_cast<float>(plant.h));
    app.begin();
  }
  // Host bytes arriving now; returns everything the firmware wrote meanwhile.
  std::string send(const std::string& bytes) {
    stream.feed(bytes);
    app.poll();
    return stream.take();
  }
  void tick() {
    app.controlTick();
    plant.step(0.001);
    hal.advanceMicros(1000);
  }
  std::string advance(unsigned long ticks) {
    for (unsigned long i = 0; i < ticks; ++i) tick();
    return stream.take();
  }
  double time() const { return linarm.ticks() * 0.001; }

  SimPlant plant;
  SimHal hal;
  BufferStream stream;
  ZeroedMessenger messengerStorage;
  CmdMessenger& messenger;
  Linarm linarm;
  LinarmApp app;
};

#endif  // LINARM_RIG_H
