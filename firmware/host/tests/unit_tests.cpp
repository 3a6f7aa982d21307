// Unit tests of the firmware logic on the host: trajectories, VSA kinematics, limits, watchdog, the strict
// wire layer on the CmdMessenger stand-in, the FSM, homing on the endstrokes and every error state.
// A tiny self-contained harness (no framework to download): `linarm_unit_tests [filter]`.
#include <math.h>
#include <stdio.h>
#include <string.h>

#include <functional>
#include <string>
#include <vector>

#include "rig.h"
#include "vsa.h"

// ------------------------------------------------------------------------------------------ harness
namespace {

struct TestCase {
  const char* name;
  std::function<void()> fn;
};
std::vector<TestCase>& registry() {
  static std::vector<TestCase> r;
  return r;
}
struct Register {
  Register(const char* n, std::function<void()> f) { registry().push_back({n, f}); }
};
int g_failures = 0;
bool g_current_failed = false;

#define TEST(name)                                \
  static void test_##name();                      \
  static Register reg_##name(#name, test_##name); \
  static void test_##name()

#define CHECK(cond)                                                        \
  do {                                                                     \
    if (!(cond)) {                                                         \
      printf("    %s:%d: CHECK(%s) failed\n", __FILE__, __LINE__, #cond);  \
      g_current_failed = true;                                             \
    }                                                                      \
  } while (0)

#define CHECK_NEAR(a, b, tol)                                                                             \
  do {                                                                                                    \
    double va_ = (a), vb_ = (b);                                                                          \
    if (!(fabs(va_ - vb_) <= (tol))) {                                                                    \
      printf("    %s:%d: %s = %.6g, expected %.6g +- %g\n", __FILE__, __LINE__, #a, va_, vb_, (double)(tol)); \
      g_current_failed = true;                                                                            \
    }                                                                                                     \
  } while (0)

// ------------------------------------------------------------------------------------------ wire helpers
std::string esc(const std::string& raw) {
  std::string out;
  for (char c : raw) {
    if (c == ',' || c == ';' || c == '/' || c == 0) out.push_back('/');
    out.push_back(c);
  }
  return out;
}

// Builds a host command: Cmd(9, seq).f(0.4).b(false).str()
struct Cmd {
  std::string s;
  Cmd(int id, int seq) { s = std::to_string(id) + "," + std::to_string(seq); }
  Cmd& i(long v) { s += "," + std::to_string(v); return *this; }
  Cmd& b(bool v) { s += v ? ",1" : ",0"; return *this; }
  Cmd& f(float v) {
    char raw[4];
    memcpy(raw, &v, 4);
    s += "," + esc(std::string(raw, 4));
    return *this;
  }
  Cmd& raw(const std::string& r) { s += "," + r; return *this; }
  std::string str() const { return s + ";"; }
};

struct Frame {
  int id;
  std::vector<std::string> fields;
  long num(size_t k) const { return k < fields.size() ? strtol(fields[k].c_str(), 0, 10) : -999; }
  float flt(size_t k) const {
    float v = NAN;
    if (k < fields.size() && fields[k].size() == 4) memcpy(&v, fields[k].data(), 4);
    return v;
  }
};

std::vector<Frame> decode(const std::string& data) {
  std::vector<Frame> frames;
  std::vector<std::string> fields(1);
  bool escaped = false;
  for (char c : data) {
    if (escaped) {
      fields.back().push_back(c);
      escaped = false;
    } else if (c == '/') {
      escaped = true;
    } else if (c == ',') {
      fields.emplace_back();
    } else if (c == ';') {
      Frame f;
      f.id = atoi(fields[0].c_str());
      f.fields.assign(fields.begin() + 1, fields.end());
      frames.push_back(f);
      fields.assign(1, std::string());
    } else {
      fields.back().push_back(c);
    }
  }
  return frames;
}

// A host talking to a Rig: numbered commands, heartbeats, all frames kept.
struct Host {
  Rig& rig;
  int seq = 0;
  std::vector<Frame> received;
  explicit Host(Rig& r) : rig(r) { received = decode(rig.stream.take()); }  // the boot IDENTIFY
  int next() { return seq = seq >= 65535 ? 1 : seq + 1; }
  Frame send(const std::string& frame) {
    std::vector<Frame> out = decode(rig.send(frame));
    received.insert(received.end(), out.begin(), out.end());
    for (const Frame& f : out)
      if (f.id == proto::MSG_ACK || f.id == proto::MSG_ERROR || f.id == proto::MSG_IDENTIFY) return f;
    return Frame{-1, {}};
  }
  // Returns 0 for an ACK, else the ERROR code.
  long cmd(Cmd c) {
    Frame f = send(c.str());
    if (f.id == proto::MSG_ACK) return 0;
    if (f.id == proto::MSG_ERROR) return f.num(2);
    return -1;
  }
  void run(double seconds, bool heartbeat = true) {
    unsigned long ticks = static_cast<unsigned long>(lround(seconds * 1000));
    std::string out;
    for (unsigned long t = 0; t < ticks; ++t) {
      if (heartbeat && rig.linarm.ticks() % 100 == 0) out += rig.send(Cmd(proto::CMD_HEARTBEAT, next()).str());
      rig.tick();
    }
    out += rig.stream.take();
    std::vector<Frame> frames = decode(out);
    received.insert(received.end(), frames.begin(), frames.end());
  }
  std::vector<int> events() const {
    std::vector<int> e;
    for (const Frame& f : received)
      if (f.id == proto::MSG_ERROR_EVENT) e.push_back(static_cast<int>(f.num(1)));
    return e;
  }
};

Rig* makeReady(RigOptions o, Host** host, proto::ControlMode mode = proto::POS_REF_BY_TARGET_POS) {
  o.startHomed = true;
  Rig* rig = new Rig(o);
  *host = new Host(*rig);
  (*host)->cmd(Cmd(proto::CMD_SET_CTRL_MODE, (*host)->next()).i(mode));
  (*host)->cmd(Cmd(proto::CMD_SET_CTRL_STATE, (*host)->next()).i(proto::ON_CTRL_STATE));
  (*host)->run(0.2);
  return rig;
}

double centreOf(const Rig& rig) { return (rig.plant.x[0] + rig.plant.x[1]) / 2; }

}  // namespace

// ------------------------------------------------------------------------------------------ trajectories
TEST(trapezoid_from_limits) {
  Trajectory t;
  CHECK(t.plan(0.10, 0.40, 0.15, 0.15, 0.0, proto::TRAPEZOIDAL) == Trajectory::PLAN_OK);
  CHECK_NEAR(t.duration(), 3.0, 1e-9);  // ta = 1 s, cruise 1 s
  t.startAt(0);
  double p, v;
  t.sample(500, &p, &v);
  CHECK_NEAR(v, 0.075, 1e-9);
  t.sample(1500, &p, &v);
  CHECK_NEAR(v, 0.15, 1e-9);
  CHECK_NEAR(p, 0.10 + 0.075 + 0.075, 1e-9);
  CHECK(!t.sample(2999, &p, &v));
  CHECK(t.sample(3001, &p, &v));
  CHECK_NEAR(p, 0.40, 1e-12);
}

TEST(trapezoid_becomes_triangular_and_exec_time) {
  Trajectory t;
  t.plan(0.0, 0.01, 0.5, 1.0, 0.0, proto::TRAPEZOIDAL);
  CHECK_NEAR(t.duration(), 2 * sqrt(0.01 / 1.0), 1e-9);
  CHECK(t.plan(0.1, 0.4, 0.5, 2.0, 3.0, proto::TRAPEZOIDAL) == Trajectory::PLAN_OK);
  t.startAt(0);
  double p, v;
  t.sample(1500, &p, &v);
  CHECK_NEAR(v, 1.5 * 0.3 / 3.0, 1e-9);
  CHECK(t.plan(0.1, 0.4, 0.1, 2.0, 1.0, proto::TRAPEZOIDAL) == Trajectory::PLAN_TOO_SHORT);
  CHECK(t.plan(0.1, 0.4, 0.0, 2.0, 0.0, proto::TRAPEZOIDAL) == Trajectory::PLAN_BAD_LIMITS);
}

TEST(cycloid) {
  Trajectory t;
  t.plan(0.10, 0.40, 0.15, 0.15, 0.0, proto::CYCLOIDAL);
  CHECK_NEAR(t.duration(), 4.0, 1e-9);  // max(2D/v, sqrt(2 pi D/a))
  t.startAt(100);
  double p, v;
  t.sample(100 + 2000, &p, &v);
  CHECK_NEAR(v, 0.15, 1e-9);
  CHECK_NEAR(p, 0.25, 1e-9);
  t.arm();
  CHECK(!t.sample(5000, &p, &v) && p == 0.10);  // armed: waits at the start
}

// ------------------------------------------------------------------------------------------ VSA
TEST(vsa_stiffness_law_in_pretension_delta) {
  CHECK_NEAR(vsa::stiffness(0.01f), 450.0, 0.01);
  CHECK_NEAR(vsa::stiffness(0.02f), 900.0, 0.01);
  CHECK_NEAR(vsa::stiffness(0.06f), 5700.0, 0.1);
  CHECK_NEAR(vsa::deltaForStiffness(2000.0f), 0.033665, 1e-5);
  CHECK_NEAR(vsa::stiffness(vsa::deltaForStiffness(2000.0f)), 2000.0, 0.5);
  float x0, x1;
  vsa::motorPositions(0.25f, 0.02f, &x0, &x1);
  CHECK_NEAR(x0, 0.20, 1e-6);
  CHECK_NEAR(x1, 0.30, 1e-6);
  CHECK_NEAR(vsa::deltaOf(x0, x1), 0.02, 1e-6);
  CHECK_NEAR(vsa::interactionForce(x0, x1, 0.25f), 0.0, 1e-4);
  CHECK(vsa::interactionForce(x0, x1, 0.26f) > 0.0f);  // held at +x: the patient pushes towards +x
}

// ------------------------------------------------------------------------------------------ limits
TEST(limits_each_condition) {
  Limits lim;
  OverCurrentTimer oc;
  SupervisionInput in;
  memset(&in, 0, sizeof in);
  in.on = true;
  in.position[0] = in.reference[0] = 0.2f;
  in.position[1] = in.reference[1] = 0.3f;
  in.handlePos = 0.25f;
  const char* msg = "";
  CHECK(checkLimits(lim, in, oc, 0, &msg) == proto::NO_ERROR);
  SupervisionInput t = in;
  t.force = 61.0f;
  CHECK(checkLimits(lim, t, oc, 0, &msg) == proto::OVER_FORCE);
  t = in;
  t.handlePos = 0.4401f;
  CHECK(checkLimits(lim, t, oc, 0, &msg) == proto::POSITION_LIMIT);
  t.handlePos = 0.4399f;
  CHECK(checkLimits(lim, t, oc, 0, &msg) == proto::NO_ERROR);
  t = in;
  t.reference[1] = 0.3201f;
  CHECK(checkLimits(lim, t, oc, 0, &msg) == proto::TRACKING_ERROR);
  t = in;
  t.endstroke[0] = true;
  CHECK(checkLimits(lim, t, oc, 0, &msg) == proto::ENDSTROKE_HIT);
  t.endstrokesDisabled = true;
  CHECK(checkLimits(lim, t, oc, 0, &msg) == proto::NO_ERROR);
  t = in;
  t.handleVel = 0.76f;
  CHECK(checkLimits(lim, t, oc, 0, &msg) == proto::OVER_VELOCITY);
  t.on = false;  // HOME: no velocity, force, position or endstroke checks
  CHECK(checkLimits(lim, t, oc, 0, &msg) == proto::NO_ERROR);
  t = in;
  t.current[1] = -5.5f;
  proto::ErrorState e = proto::NO_ERROR;
  uint32_t tick = 0;
  for (; tick < 100 && e == proto::NO_ERROR; ++tick) e = checkLimits(lim, t, oc, tick, &msg);
  CHECK(e == proto::OVER_CURRENT);
  CHECK(tick == 51);  // 50 ms above the limit
  t.demo = true;
  t.reference[0] = 0.0f;
  CHECK(checkLimits(lim, t, oc, 0, &msg) == proto::NO_ERROR);  // demo: no robot to track
}

TEST(watchdog_arms_on_the_first_byte) {
  HostWatchdog w;
  CHECK(!w.expired(100000));
  w.feed(1000);
  CHECK(!w.expired(1250));
  CHECK(w.expired(1251));
}

// ------------------------------------------------------------------------------------------ wire
TEST(cmdmessenger_stand_in_skips_empty_fields_and_wraps_overflow) {
  Rig rig;
  Host host(rig);
  Frame f = host.send("9,1,,,;");  // empty fields vanish: moveCentreTo with no arguments
  CHECK(f.id == proto::MSG_ERROR && f.num(0) == 1 && f.num(1) == 9 && f.num(2) == proto::BAD_ARGUMENT);
  std::string overlong = "9,1," + std::string(70, 'A') + ";";
  std::vector<Frame> out = decode(rig.send(overlong));
  CHECK(!out.empty());
  for (const Frame& r : out) CHECK(r.id == proto::MSG_ERROR && r.num(1) == 0);  // its tail ran as command 0
  CHECK(rig.messenger.overflows() == 1);
  f = host.send("\x07zz;");  // garbage: command 0 without a readable seq
  CHECK(f.id == proto::MSG_ERROR && f.num(0) == 0 && f.num(1) == 0 && f.num(2) == proto::BAD_ARGUMENT);
  f = host.send(";");  // a lone ';' is ignored (empty buffer)
  CHECK(f.id == -1);
  f = host.send("0,77;");
  CHECK(f.id == proto::MSG_IDENTIFY && f.num(0) == 77 && f.fields[2] == "LINarm2");
}

TEST(strict_arguments) {
  Rig rig;
  Host host(rig);
  CHECK(host.cmd(Cmd(proto::CMD_SET_DEMO, 5).raw("true")) == proto::BAD_ARGUMENT);
  CHECK(host.cmd(Cmd(proto::CMD_SET_DEMO, 5).i(2)) == proto::BAD_ARGUMENT);
  CHECK(host.cmd(Cmd(proto::CMD_SET_DEMO, 5).b(true).b(true)) == proto::BAD_ARGUMENT);  // extra argument
  CHECK(host.cmd(Cmd(proto::CMD_SET_CTRL_STATE, 5).i(3)) == proto::OUT_OF_RANGE);       // enum range
  CHECK(host.cmd(Cmd(proto::CMD_SET_CTRL_STATE, 5).raw("1x")) == proto::BAD_ARGUMENT);
  CHECK(host.cmd(Cmd(proto::CMD_SET_MAX_FORCE, 5).raw("ab")) == proto::BAD_ARGUMENT);    // short float
  CHECK(host.cmd(Cmd(proto::CMD_SET_MAX_FORCE, 5).f(NAN)) == proto::BAD_ARGUMENT);
  CHECK(host.cmd(Cmd(proto::CMD_START_DATA_STREAM, 5).f(2.0f)) == proto::OUT_OF_RANGE);   // table: 0.001..1
  Frame f = host.send("45,7;");
  CHECK(f.id == proto::MSG_ERROR && f.num(0) == 7 && f.num(1) == 45 && f.num(2) == proto::UNKNOWN_COMMAND);
  f = host.send("4,70000,0;");
  CHECK(f.id == proto::MSG_ERROR && f.num(0) == 0 && f.num(2) == proto::BAD_ARGUMENT);  // bad seq -> seq 0
  // a float whose bytes need escaping (0.0f is four NULs) arrives intact
  CHECK(host.cmd(Cmd(proto::CMD_SET_TRIGGER_PARAMETER, 6).f(0.0f)) == 0);
  f = host.send(Cmd(proto::CMD_GET_PID_TUNINGS, 8).i(1).str());
  CHECK(f.id == proto::MSG_ACK && f.num(2) == 1 && f.flt(3) == cfg::PID_KP);
}

// ------------------------------------------------------------------------------------------ FSM
TEST(fsm_refuses_on_before_homing) {
  Rig rig;
  Host host(rig);
  CHECK(host.cmd(Cmd(proto::CMD_SET_CTRL_STATE, host.next()).i(proto::ON_CTRL_STATE)) == proto::NOT_HOMED);
  CHECK(host.cmd(Cmd(proto::CMD_MOVE_CENTRE_TO, host.next()).f(0.3f).f(0.1f).f(0.1f).f(0).b(false)) ==
        proto::WRONG_STATE);
  CHECK(rig.linarm.controlState() == proto::IDLE_CTRL_STATE);
}

TEST(homing_on_the_endstrokes) {
  RigOptions o;
  o.centre = 0.20;
  Rig rig(o);
  Host host(rig);
  CHECK(host.cmd(Cmd(proto::CMD_GO_TO_HOME, host.next())) == 0);
  CHECK(rig.linarm.controlState() == proto::HOME_CTRL_STATE);
  std::vector<int> seen;
  int closures[2] = {0, 0};
  bool was[2] = {false, false};
  double t0 = rig.time();
  for (int k = 0; k < 10000 && rig.linarm.homeState() != proto::HOME_DONE; ++k) {
    host.run(0.001);
    if (seen.empty() || seen.back() != rig.linarm.homeState()) seen.push_back(rig.linarm.homeState());
    for (int i = 0; i < 2; ++i) {
      bool now = rig.hal.endstroke(i);
      if (now && !was[i]) ++closures[i];
      was[i] = now;
    }
  }
  std::vector<int> expected = {proto::HOME_SEEK_MIN, proto::HOME_SEEK_MAX, proto::HOME_MOVE_TO_HOME, proto::HOME_DONE};
  CHECK(seen == expected);
  CHECK(rig.time() - t0 <= 5.0);
  printf("    homing took %.3f s\n", rig.time() - t0);
  CHECK(closures[0] == 1 && closures[1] == 1);
  CHECK(rig.linarm.errorState() == proto::NO_ERROR && rig.linarm.initialized());
  host.run(0.01);
  const Measurement& m = rig.linarm.measurement();
  CHECK_NEAR((m.x[0] + m.x[1]) / 2, 0.25, 0.002);
  CHECK_NEAR(centreOf(rig), 0.25, 0.002);  // measured = true: the encoders are referenced
  CHECK_NEAR(vsa::deltaOf(m.x[0], m.x[1]), 0.02, 0.002);
  CHECK_NEAR(m.h, rig.plant.h, 0.001);
  CHECK(host.cmd(Cmd(proto::CMD_SET_CTRL_STATE, host.next()).i(proto::ON_CTRL_STATE)) == 0);
}

TEST(homing_busy_and_idle_always_allowed) {
  Rig rig;
  Host host(rig);
  CHECK(host.cmd(Cmd(proto::CMD_SET_CTRL_STATE, host.next()).i(proto::HOME_CTRL_STATE)) == 0);
  host.run(0.2);
  CHECK(host.cmd(Cmd(proto::CMD_SET_CTRL_STATE, host.next()).i(proto::ON_CTRL_STATE)) == proto::BUSY);
  CHECK(host.cmd(Cmd(proto::CMD_SET_CTRL_MODE, host.next()).i(1)) == proto::BUSY);
  CHECK(host.cmd(Cmd(proto::CMD_SET_DEMO, host.next()).b(true)) == proto::WRONG_STATE);
  CHECK(host.cmd(Cmd(proto::CMD_SET_CTRL_STATE, host.next()).i(proto::IDLE_CTRL_STATE)) == 0);
  CHECK(rig.linarm.controlState() == proto::IDLE_CTRL_STATE && !rig.plant.enabled);
}

TEST(trigger_exercise_motion_is_trapezoidal) {
  RigOptions o;
  o.centre = 0.10;
  Host* host;
  Rig* rig = makeReady(o, &host);
  CHECK(host->cmd(Cmd(proto::CMD_MOVE_DELTA_TO, host->next()).f(0.010f).f(0.15f).f(0.15f).f(0).b(false)) == 0);
  host->run(1.0);
  CHECK_NEAR(vsa::deltaOf(rig->linarm.measurement().x[0], rig->linarm.measurement().x[1]), 0.010, 0.001);
  CHECK(host->cmd(Cmd(proto::CMD_MOVE_CENTRE_TO, host->next()).f(0.40f).f(0.15f).f(0.15f).f(0).b(false)) == 0);
  double peak = 0.0, atHalf = 0.0, atPlateau = 0.0;
  for (int k = 0; k < 4000; ++k) {
    host->run(0.001);
    double v = (rig->plant.v[0] + rig->plant.v[1]) / 2;
    if (v > peak) peak = v;
    if (k == 500) atHalf = v;
    if (k == 1500) atPlateau = v;
  }
  CHECK_NEAR(centreOf(*rig), 0.40, 0.005);
  CHECK(peak <= 0.15 * 1.05);
  CHECK_NEAR(atHalf, 0.075, 0.01);
  CHECK_NEAR(atPlateau, 0.15, 0.005);
  CHECK(rig->linarm.errorState() == proto::NO_ERROR);
  printf("    reached %.4f m, peak %.4f m/s\n", centreOf(*rig), peak);
  delete host;
  delete rig;
}

// ------------------------------------------------------------------------------------------ errors
namespace {
void expectTrip(Host& host, proto::ErrorState expected, double seconds = 3.0) {
  for (int k = 0; k < seconds / 0.05 && host.rig.linarm.errorState() == proto::NO_ERROR; ++k) host.run(0.05);
  CHECK(host.rig.linarm.errorState() == expected);
  CHECK(host.rig.linarm.controlState() == proto::IDLE_CTRL_STATE);
  CHECK(host.rig.linarm.commandedCurrent(0) == 0.0f && host.rig.linarm.commandedCurrent(1) == 0.0f);
  CHECK(!host.rig.plant.enabled);
  std::vector<int> ev = host.events();
  CHECK(ev.size() == 1 && ev[0] == expected);
  CHECK(host.cmd(Cmd(proto::CMD_SET_CTRL_STATE, host.next()).i(proto::ON_CTRL_STATE)) == proto::IN_ERROR);
  CHECK(host.cmd(Cmd(proto::CMD_RESET_ERROR, host.next())) == 0);
  host.run(0.1);
  CHECK(host.rig.linarm.errorState() == proto::NO_ERROR);
}
}  // namespace

TEST(error_watchdog) {
  Host* host;
  Rig* rig = makeReady(RigOptions(), &host);
  host->send(Cmd(proto::CMD_HEARTBEAT, host->next()).str());
  host->run(0.25, false);
  CHECK(rig->linarm.controlState() == proto::ON_CTRL_STATE);  // 250 ms: still fine
  host->run(0.01, false);
  CHECK(rig->linarm.errorState() == proto::WATCHDOG);
  expectTrip(*host, proto::WATCHDOG);
  delete host;
  delete rig;
}

TEST(error_tracking) {
  Host* host;
  Rig* rig = makeReady(RigOptions(), &host);
  host->cmd(Cmd(proto::CMD_SET_MAX_TRACKING_ERROR, host->next()).f(1e-5f));
  host->cmd(Cmd(proto::CMD_MOVE_CENTRE_TO, host->next()).f(0.30f).f(0.2f).f(1.0f).f(0).b(false));
  expectTrip(*host, proto::TRACKING_ERROR);
  delete host;
  delete rig;
}

TEST(error_endstroke_hit_and_disable) {
  RigOptions o;
  o.centre = 0.40;
  Host* host;
  Rig* rig = makeReady(o, &host);
  host->cmd(Cmd(proto::CMD_SET_POS_LIMIT, host->next()).f(0.0f).f(0.5f));
  host->cmd(Cmd(proto::CMD_MOVE_CENTRE_TO, host->next()).f(0.48f).f(0.1f).f(0.5f).f(0).b(false));
  expectTrip(*host, proto::ENDSTROKE_HIT);
  CHECK(rig->plant.x[1] >= rig->plant.p.switchMax);
  delete host;
  delete rig;
  rig = makeReady(o, &host);
  host->cmd(Cmd(proto::CMD_DISABLE_ENDSTROKES, host->next()).b(true));
  host->cmd(Cmd(proto::CMD_SET_POS_LIMIT, host->next()).f(0.0f).f(0.5f));
  host->cmd(Cmd(proto::CMD_SET_MAX_TRACKING_ERROR, host->next()).f(0.05f));
  host->cmd(Cmd(proto::CMD_MOVE_CENTRE_TO, host->next()).f(0.445f).f(0.1f).f(0.5f).f(0).b(false));
  host->run(1.5);
  CHECK(rig->linarm.errorState() == proto::NO_ERROR && rig->plant.x[1] >= rig->plant.p.switchMax - 1e-3);
  delete host;
  delete rig;
}

TEST(error_over_force) {
  Host* host;
  Rig* rig = makeReady(RigOptions(), &host);
  host->cmd(Cmd(proto::CMD_SET_MAX_FORCE, host->next()).f(5.0f));
  rig->plant.externalForce = 10.0;  // the patient pushes
  expectTrip(*host, proto::OVER_FORCE);
  delete host;
  delete rig;
}

TEST(error_over_current) {
  Host* host;
  Rig* rig = makeReady(RigOptions(), &host);
  host->cmd(Cmd(proto::CMD_SET_MAX_CURRENT, host->next()).f(0.05f));  // 8 N friction needs 0.4 A
  host->cmd(Cmd(proto::CMD_MOVE_CENTRE_TO, host->next()).f(0.30f).f(0.1f).f(0.5f).f(0).b(false));
  expectTrip(*host, proto::OVER_CURRENT);
  delete host;
  delete rig;
}

TEST(error_over_velocity) {
  Host* host;
  Rig* rig = makeReady(RigOptions(), &host);
  host->cmd(Cmd(proto::CMD_SET_MAX_VELOCITY, host->next()).f(0.02f));
  rig->plant.externalForce = 20.0;  // a sudden push
  expectTrip(*host, proto::OVER_VELOCITY);
  delete host;
  delete rig;
}

TEST(error_position_limit) {
  Host* host;
  Rig* rig = makeReady(RigOptions(), &host);
  host->cmd(Cmd(proto::CMD_SET_POS_LIMIT, host->next()).f(0.08f).f(0.15f));  // handle at 0.20 > 0.15 + 0.02
  expectTrip(*host, proto::POSITION_LIMIT);
  delete host;
  delete rig;
}

TEST(error_homing_failed) {
  RigOptions o;
  o.params.switchMin = -0.01;  // the min switch never closes
  Rig rig(o);
  Host host(rig);
  CHECK(host.cmd(Cmd(proto::CMD_SET_HOME_PARAMETER, host.next()).f(0.25f).f(0.02f).f(0.2f)) == 0);
  CHECK(host.cmd(Cmd(proto::CMD_SET_MAX_CURRENT, host.next()).f(6.0f)) == 0);
  CHECK(host.cmd(Cmd(proto::CMD_GO_TO_HOME, host.next())) == 0);
  expectTrip(host, proto::HOMING_FAILED, 8.0);
  CHECK(!rig.linarm.initialized());
}

TEST(no_blocking_in_the_control_loop) {
  // A full second of control with the stream on: every tick returns, frames go out at the set period.
  Host* host;
  Rig* rig = makeReady(RigOptions(), &host);
  host->received.clear();
  CHECK(host->cmd(Cmd(proto::CMD_START_DATA_STREAM, host->next()).f(0.005f)) == 0);
  host->run(1.0);
  int vsaFrames = 0, motorFrames = 0, stateFrames = 0;
  for (const Frame& f : host->received) {
    vsaFrames += f.id == proto::MSG_VSA_STATE;
    motorFrames += f.id == proto::MSG_MOTOR_STATE;
    stateFrames += f.id == proto::MSG_LINARM_STATE;
  }
  CHECK(vsaFrames >= 199 && vsaFrames <= 201);
  CHECK(motorFrames == 2 * vsaFrames);
  CHECK(stateFrames >= 20 && stateFrames <= 22);
  delete host;
  delete rig;
}

// ------------------------------------------------------------------------------------------ the DUE's ABI
TEST(abi_is_the_dues) {
  // plain char is unsigned on the DUE; the host build says so too (-funsigned-char), the ARM build natively
  CHECK(static_cast<char>(-1) > 0);
#if defined(__arm__)
  CHECK(sizeof(int) == 4 && sizeof(long) == 4 && sizeof(void*) == 4);  // ILP32, as the Cortex-M3
#endif
  // An overlong frame whose tail starts with an integer above 2^31: the DUE's atol saturates (id 255,
  // UNKNOWN_COMMAND); an LP64 atol would have read 3 (resetError) and ACKed it.
  Rig rig;
  Host host(rig);
  Frame f = host.send(";27,1," + std::string(58, '9') + "4294967299,5;");
  CHECK(f.id == proto::MSG_ERROR && f.num(0) == 5 && f.num(1) == 255 && f.num(2) == proto::UNKNOWN_COMMAND);
}

TEST(first_frame_carries_its_id) {
  // CmdMessenger 4.2.0 leaves startCommand to the memory it is built on: the rig zeroes it (ZeroedMessenger).
  Rig* rig = new Rig();
  std::string boot = rig->stream.take();
  CHECK(boot.compare(0, 4, "100,") == 0);
  delete rig;
}

TEST(envelope_lock) {
  Host* host;
  Rig* rig = makeReady(RigOptions(), &host);
  CHECK(host->cmd(Cmd(proto::CMD_SET_MAX_VELOCITY, host->next()).f(0.3f)) == 0);
  Frame ack = host->send(Cmd(proto::CMD_LOCK_ENVELOPE, host->next()).str());
  CHECK(ack.id == proto::MSG_ACK && ack.fields.size() == 9);
  CHECK_NEAR(ack.flt(2), 0.3, 1e-7);
  CHECK(host->cmd(Cmd(proto::CMD_SET_MAX_VELOCITY, host->next()).f(0.31f)) == proto::LOCKED);
  CHECK(host->cmd(Cmd(proto::CMD_SET_MAX_VELOCITY, host->next()).f(0.2f)) == 0);
  CHECK(host->cmd(Cmd(proto::CMD_SET_MAX_VELOCITY, host->next()).f(0.3f)) == 0);
  CHECK(host->cmd(Cmd(proto::CMD_DISABLE_ENDSTROKES, host->next()).b(true)) == proto::LOCKED);
  CHECK(host->cmd(Cmd(proto::CMD_SET_PID_TUNINGS, host->next()).i(0).f(1.0f).f(0.0f).f(0.0f)) == proto::LOCKED);
  CHECK(rig->linarm.envelopeLocked() && !rig->linarm.serviceMode());
  CHECK_NEAR(rig->linarm.pid(0).kp, cfg::PID_KP, 1e-3);
  delete host;
  delete rig;
}

int main(int argc, char** argv) {
  const char* filter = argc > 1 ? argv[1] : "";
  int run = 0;
  for (const TestCase& t : registry()) {
    if (*filter && !strstr(t.name, filter)) continue;
    g_current_failed = false;
    printf("[ RUN  ] %s\n", t.name);
    t.fn();
    printf(g_current_failed ? "[ FAIL ] %s\n" : "[  OK  ] %s\n", t.name);
    g_failures += g_current_failed;
    ++run;
  }
  printf("%d tests, %d failed\n", run, g_failures);
  return g_failures == 0 && run > 0 ? 0 : 1;
}
