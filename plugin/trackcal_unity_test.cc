// The plugin's C ABI, called as Unity calls it (through the shared library), against our VRPN
// server on loopback.
#include "plugin/trackcal_unity.h"

#include <gtest/gtest.h>

#include <chrono>
#include <functional>
#include <string>
#include <thread>

#include "plugin/unity_axes.h"
#include "tests/test_utils.h"
#include "vrpn_server/server/server.h"

namespace trackcal {
namespace {

using Clock = std::chrono::steady_clock;
using vrpn::Timestamp;

std::unique_ptr<vrpn::VrpnServer> StartServer(int port = 0) {
  auto catalog = std::make_shared<vrpn::ServerCatalog>();
  vrpn::TrackerSpec spec;
  spec.name = "Tracker0";
  spec.num_sensors = 4;
  catalog->AddTracker(spec);
  catalog->AddButton(vrpn::ButtonSpec{"Stylus0", 2});
  vrpn::ServerOptions options;
  options.bind_address = "127.0.0.1";
  options.port = port;
  auto server = std::make_unique<vrpn::VrpnServer>(catalog, options, [](const std::string&) {});
  server->Start();
  return server;
}

// Publishes until pred() holds or the (load-tolerant) timeout passes: the plugin connects on its
// own thread, so poses published before it has subscribed are not seen.
bool PublishUntil(const std::function<void()>& publish, const std::function<bool()>& pred,
                  double timeout_s = 20.0) {
  const auto end = Clock::now() + std::chrono::duration<double>(timeout_s);
  while (Clock::now() < end) {
    if (pred()) return true;
    publish();
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  return pred();
}

struct Handle {
  TrackcalUnityTracker* t;
  explicit Handle(const std::string& name, const char* axes = nullptr)
      : t(trackcal_unity_open(name.c_str(), axes)) {}
  ~Handle() { trackcal_unity_close(t); }
};

TEST(TrackcalUnity, AbiVersion) {
  EXPECT_EQ(trackcal_unity_abi_version(), TRACKCAL_UNITY_ABI_VERSION);
}

TEST(TrackcalUnity, BadArgumentsReturnAnErrorThatSaysWhy) {
  EXPECT_EQ(trackcal_unity_open(nullptr, nullptr), nullptr);
  EXPECT_NE(std::string(trackcal_unity_last_error()).find("null"), std::string::npos);
  EXPECT_EQ(trackcal_unity_open("Tracker0", nullptr), nullptr);  // no "@host"
  EXPECT_NE(std::string(trackcal_unity_last_error()).find("Tracker0"), std::string::npos)
      << trackcal_unity_last_error();
  // A stray blank (an Inspector field typed with a leading space) names where it is.
  EXPECT_EQ(trackcal_unity_open(" Tracker0@localhost", nullptr), nullptr);
  EXPECT_NE(
      std::string(trackcal_unity_last_error()).find("blank or control character at position 1"),
      std::string::npos)
      << trackcal_unity_last_error();
  EXPECT_EQ(trackcal_unity_open("Tracker0@localhost", "x,y,z"), nullptr);
  EXPECT_NE(std::string(trackcal_unity_last_error()).find("mirrored"), std::string::npos);

  Handle h("Tracker0@tcp://127.0.0.1:1");  // nothing listens: the handle keeps retrying
  ASSERT_NE(h.t, nullptr) << trackcal_unity_last_error();
  EXPECT_STREQ(trackcal_unity_last_error(), "");
  TrackcalUnityPose pose;
  EXPECT_EQ(trackcal_unity_get_pose(h.t, -1, &pose), TRACKCAL_UNITY_ERROR_ARGUMENT);
  EXPECT_NE(std::string(trackcal_unity_last_error()).find("sensor -1"), std::string::npos);
  EXPECT_EQ(trackcal_unity_get_pose(h.t, 0, nullptr), TRACKCAL_UNITY_ERROR_ARGUMENT);
  EXPECT_EQ(trackcal_unity_get_pose(h.t, 0, &pose), TRACKCAL_UNITY_NO_POSE);
  EXPECT_EQ(pose.valid, 0);
  TrackcalUnityStatus status;
  EXPECT_EQ(trackcal_unity_get_status(h.t, &status), TRACKCAL_UNITY_OK);
  EXPECT_EQ(status.connected, 0);
  EXPECT_EQ(trackcal_unity_get_status(nullptr, &status), TRACKCAL_UNITY_ERROR_ARGUMENT);
  const double p[3] = {0, 0, 0}, q[4] = {0, 0, 0, 1};
  double up[3], uq[4];
  EXPECT_EQ(trackcal_unity_convert("x,y,q", p, q, up, uq), TRACKCAL_UNITY_ERROR_ARGUMENT);
  EXPECT_NE(std::string(trackcal_unity_last_error()).find("\"q\""), std::string::npos);
  trackcal_unity_close(nullptr);
}

TEST(TrackcalUnity, ConvertIsToUnity) {
  auto& rng = testing::TestRng();
  const auto axes = unity::ParseAxisMap("x,y,-z");
  for (int i = 0; i < 20; ++i) {
    const Rigid3d pose(testing::RandomRotation(rng), Eigen::Vector3d::Random());
    const double p[3] = {pose.translation.x(), pose.translation.y(), pose.translation.z()};
    const double q[4] = {pose.rotation.x(), pose.rotation.y(), pose.rotation.z(),
                         pose.rotation.w()};
    double up[3], uq[4];
    ASSERT_EQ(trackcal_unity_convert("x,y,-z", p, q, up, uq), TRACKCAL_UNITY_OK);
    const auto expected = unity::ToUnity(axes, pose);
    for (int k = 0; k < 3; ++k) EXPECT_EQ(up[k], expected.position[k]);
    EXPECT_EQ(uq[0], expected.rotation.x());
    EXPECT_EQ(uq[3], expected.rotation.w());
    // The common right-handed -> Unity rule for a z flip: (x, y, -z) and (-qx, -qy, qz, qw).
    EXPECT_EQ(up[2], -p[2]);
    EXPECT_EQ(uq[0], -q[0]);
    EXPECT_EQ(uq[1], -q[1]);
    EXPECT_EQ(uq[2], q[2]);
  }
}

void ExpectServedPoses(const std::string& name, bool udp) {
  auto server = StartServer();
  const std::string full = name + std::to_string(server->port());
  Handle h(full);
  ASSERT_NE(h.t, nullptr) << trackcal_unity_last_error();
  auto& rng = testing::TestRng();
  const Rigid3d pose0(testing::RandomRotation(rng), Eigen::Vector3d(0.3, -0.2, 0.45));
  const Rigid3d pose2(testing::RandomRotation(rng), Eigen::Vector3d(-0.1, 0.25, 0.6));
  const Timestamp time{1795255605u, 250000u};
  TrackcalUnityPose got0, got2;
  ASSERT_TRUE(PublishUntil(
      [&] {
        server->PublishPose(0, 0, pose0, time);
        server->PublishPose(0, 2, pose2, time);
      },
      [&] {
        return trackcal_unity_get_pose(h.t, 0, &got0) == TRACKCAL_UNITY_OK &&
               trackcal_unity_get_pose(h.t, 2, &got2) == TRACKCAL_UNITY_OK;
      }))
      << full;
  const auto axes = unity::ParseAxisMap(unity::kDefaultAxes);
  for (const auto& [got, sent, sensor] : {std::tuple{got0, pose0, 0}, std::tuple{got2, pose2, 2}}) {
    EXPECT_EQ(got.sensor, sensor);
    EXPECT_EQ(got.valid, 1);
    EXPECT_GE(got.reports, 1u);
    // The wire carries doubles: the tracker frame arrives bit-exact.
    EXPECT_EQ(got.tracker_px, sent.translation.x());
    EXPECT_EQ(got.tracker_py, sent.translation.y());
    EXPECT_EQ(got.tracker_pz, sent.translation.z());
    EXPECT_EQ(got.tracker_qx, sent.rotation.x());
    EXPECT_EQ(got.tracker_qw, sent.rotation.w());
    const auto u = unity::ToUnity(axes, sent);
    EXPECT_EQ(got.unity_px, u.position.x());
    EXPECT_EQ(got.unity_py, u.position.y());
    EXPECT_EQ(got.unity_pz, u.position.z());
    EXPECT_EQ(got.unity_qx, u.rotation.x());
    EXPECT_EQ(got.unity_qy, u.rotation.y());
    EXPECT_EQ(got.unity_qz, u.rotation.z());
    EXPECT_EQ(got.unity_qw, u.rotation.w());
    EXPECT_DOUBLE_EQ(got.time_s, time.Seconds());
    EXPECT_GE(got.age_s, 0.0);
    EXPECT_LT(got.age_s, 20.0);
  }
  TrackcalUnityPose none;
  EXPECT_EQ(trackcal_unity_get_pose(h.t, 1, &none), TRACKCAL_UNITY_NO_POSE);

  // A text from the server (a resetting tracker) reaches the scene.
  char text[64];
  int32_t severity = -1;
  ASSERT_TRUE(PublishUntil(
      [&] { server->PublishText(0, vrpn::TextSeverity::kWarning, "Resetting the tracker"); },
      [&] { return trackcal_unity_last_text(h.t, text, sizeof(text), &severity) > 0; }));
  EXPECT_STREQ(text, "Resetting the tracker");
  EXPECT_EQ(severity, 1);
  char small[5];
  EXPECT_EQ(trackcal_unity_last_text(h.t, small, sizeof(small), nullptr), 21);  // the full length
  EXPECT_STREQ(small, "Rese");
  // A cut never splits a UTF-8 character (C# would decode half of one as U+FFFD): "Ger\xc3\xa4t"
  // in 5 bytes is "Ger", not "Ger\xc3".
  ASSERT_TRUE(PublishUntil(
      [&] { server->PublishText(0, vrpn::TextSeverity::kNormal, "Ger\xc3\xa4t bereit"); },
      [&] {
        return trackcal_unity_last_text(h.t, text, sizeof(text), &severity) > 0 &&
               std::string(text).starts_with("Ger");
      }));
  EXPECT_EQ(trackcal_unity_last_text(h.t, small, sizeof(small), nullptr), 13);  // the full length
  EXPECT_STREQ(small, "Ger");

  TrackcalUnityStatus status;
  ASSERT_EQ(trackcal_unity_get_status(h.t, &status), TRACKCAL_UNITY_OK);
  EXPECT_EQ(status.connected, 1);
  EXPECT_EQ(status.device_served, 1);
  EXPECT_EQ(status.connections, 1u);
  EXPECT_EQ(status.udp, udp ? 1 : 0);  // lob mode: the reports came over the UDP data channel
  EXPECT_GE(status.reports, 2u);
  EXPECT_GE(status.texts, 1u);

  // The server goes away and comes back on the same port: the handle reconnects on its own.
  const int port = server->port();
  server.reset();
  auto catalog = std::make_shared<vrpn::ServerCatalog>();
  vrpn::TrackerSpec spec;
  spec.name = "Tracker0";
  spec.num_sensors = 4;
  catalog->AddTracker(spec);
  vrpn::ServerOptions options;
  options.bind_address = "127.0.0.1";
  options.port = port;
  vrpn::VrpnServer again(catalog, options, [](const std::string&) {});
  again.Start();
  const Rigid3d moved(pose0.rotation, pose0.translation + Eigen::Vector3d(0.01, 0, 0));
  ASSERT_TRUE(PublishUntil([&] { again.PublishPose(0, 0, moved, Timestamp::Now()); },
                           [&] {
                             return trackcal_unity_get_pose(h.t, 0, &got0) == TRACKCAL_UNITY_OK &&
                                    got0.tracker_px == moved.translation.x();
                           }));
  ASSERT_EQ(trackcal_unity_get_status(h.t, &status), TRACKCAL_UNITY_OK);
  EXPECT_GE(status.connections, 2u);
}

TEST(TrackcalUnity, ServedPosesOverDirectTcp) {
  ExpectServedPoses("Tracker0@tcp://127.0.0.1:", false);
}

TEST(TrackcalUnity, ServedPosesOverUdpWithCallBack) {
  ExpectServedPoses("Tracker0@127.0.0.1:", true);
}

TEST(TrackcalUnity, ClosingWhileConnectingReturnsPromptly) {
  const auto start = Clock::now();
  for (int i = 0; i < 5; ++i) {
    TrackcalUnityTracker* t = trackcal_unity_open("Tracker0@127.0.0.1:1", nullptr);
    ASSERT_NE(t, nullptr);
    trackcal_unity_close(t);
  }
  // The network thread polls in 50 ms steps; 5 s leaves room for a loaded machine.
  EXPECT_LT(std::chrono::duration<double>(Clock::now() - start).count(), 5.0);
}

// Unity closes handles on its main thread (OnDisable, leaving play mode, a scene change): the
// network thread's 50 ms wait must not be sat out. Each handle has run 120 ms, so its thread is
// mid-wait (a refused connect, then retries: nothing else wakes it). Before the wake-up, each
// close took 0-50 ms (measured: 0.28 s for ten, ~0.5 s expected for twenty); 0.2 s for twenty
// leaves a loaded machine 10 ms per close, where a woken close takes well under 1 ms.
TEST(TrackcalUnity, ClosingDoesNotSitOutTheNetworkThreadsWait) {
  for (const char* name : {"Tracker0@tcp://127.0.0.1:1", "Tracker0@127.0.0.1:1"}) {
    double total_s = 0;
    for (int i = 0; i < 20; ++i) {
      TrackcalUnityTracker* t = trackcal_unity_open(name, nullptr);
      ASSERT_NE(t, nullptr) << trackcal_unity_last_error();
      std::this_thread::sleep_for(std::chrono::milliseconds(120));
      const auto start = Clock::now();
      trackcal_unity_close(t);
      total_s += std::chrono::duration<double>(Clock::now() - start).count();
    }
    EXPECT_LT(total_s, 0.2) << name;
  }
}

TEST(TrackcalUnity, AStylusButtonIsReadAndNoPressIsLost) {
  auto server = StartServer();
  Handle h("Stylus0@tcp://127.0.0.1:" + std::to_string(server->port()));
  ASSERT_NE(h.t, nullptr) << trackcal_unity_last_error();
  int32_t pressed = -1;
  uint64_t presses = 99;
  // The server sends the states on connect: both buttons known, released, no press yet.
  ASSERT_TRUE(PublishUntil(
      [] {},
      [&] { return trackcal_unity_get_button(h.t, 1, &pressed, &presses) == TRACKCAL_UNITY_OK; }));
  EXPECT_EQ(pressed, 0);
  EXPECT_EQ(presses, 0u);
  // A press and a release between two reads (two frames) still counts once. Wait for both: a
  // read between the client thread's handling of the press and of the release sees the press
  // alone (presses 1, pressed 1), which is right at that moment.
  server->PublishButton(0, 1, true, Timestamp::Now());
  server->PublishButton(0, 1, false, Timestamp::Now());
  ASSERT_TRUE(PublishUntil([] {},
                           [&] {
                             trackcal_unity_get_button(h.t, 1, &pressed, &presses);
                             return presses >= 1 && pressed == 0;
                           }));
  EXPECT_EQ(presses, 1u);
  server->PublishButton(0, 1, true, Timestamp::Now());
  ASSERT_TRUE(PublishUntil([] {},
                           [&] {
                             trackcal_unity_get_button(h.t, 1, &pressed, &presses);
                             return pressed == 1;
                           }));
  EXPECT_EQ(presses, 2u);

  // The server goes away with the button held: it is not reported pressed while disconnected (a
  // digitising scene would keep drawing), and presses are kept.
  const int port = server->port();
  server.reset();
  ASSERT_TRUE(PublishUntil([] {},
                           [&] {
                             trackcal_unity_get_button(h.t, 1, &pressed, &presses);
                             return pressed == 0;
                           }));
  EXPECT_EQ(presses, 2u);
  // Back on the same port: a press on the new connection is counted.
  server = StartServer(port);
  TrackcalUnityStatus status;
  ASSERT_TRUE(PublishUntil([] {}, [&] {
    return trackcal_unity_get_status(h.t, &status) == TRACKCAL_UNITY_OK && status.connected == 1;
  }));
  ASSERT_TRUE(PublishUntil([&] { server->PublishButton(0, 1, true, Timestamp::Now()); },
                           [&] {
                             trackcal_unity_get_button(h.t, 1, &pressed, &presses);
                             return pressed == 1;
                           }));
  EXPECT_EQ(presses, 3u);
  EXPECT_EQ(trackcal_unity_get_button(h.t, 0, &pressed, &presses), TRACKCAL_UNITY_OK);
  EXPECT_EQ(pressed, 0);
  EXPECT_EQ(trackcal_unity_get_button(h.t, 7, &pressed, &presses), TRACKCAL_UNITY_NO_BUTTON);
  EXPECT_EQ(trackcal_unity_get_button(h.t, -1, &pressed, &presses), TRACKCAL_UNITY_ERROR_ARGUMENT);
  EXPECT_NE(std::string(trackcal_unity_last_error()).find("button -1"), std::string::npos);
  EXPECT_EQ(trackcal_unity_get_button(h.t, 0, nullptr, &presses), TRACKCAL_UNITY_ERROR_ARGUMENT);
}

}  // namespace
}  // namespace trackcal
