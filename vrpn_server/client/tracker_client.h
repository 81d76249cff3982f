// A VRPN tracker client, as the reference vrpn_Tracker_Remote connects:
//   "Tracker0@tcp://host:port", "Tracker0@tcp://host", "Tracker0@tcp:host:port"  direct TCP;
//   "Tracker0@host", "Tracker0@host:port", "Tracker0@x-vrpn://host:port"        UDP lob + TCP
//   call-back,
// with a UDP data channel in lob mode. It pings until the server answers (a missing pong means the
// device name is not served), decodes Pos_Quat into poses and reconnects on its own.
//
// Single-threaded: call Poll() from one thread, or Start() a background thread that does. Callbacks
// run on that thread. On Start()'s thread an exception from Poll() (a callback's, a failure to
// start a thread or to allocate) drops the connection, which is made again, rather than ending the
// process; Poll() itself lets it through.

#pragma once

#include <atomic>
#include <functional>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>

#include "core/pose.h"
#include "vrpn_server/protocol/connection.h"
#include "vrpn_server/protocol/payloads.h"
#include "vrpn_server/protocol/wire.h"

namespace trackcal::vrpn {

struct VrpnName {
  std::string device;  // sender name, e.g. "Tracker0"
  std::string host;
  int port = kDefaultPort;
  bool tcp = false;  // direct TCP (name contains "tcp:"); otherwise lob + call-back
};
// Parses "Device@connection" (the text before the first '@' is the device, as the reference reads
// it). Throws std::invalid_argument naming the string.
VrpnName ParseVrpnName(const std::string& name);

struct TrackerClientOptions {
  // Ping period until the first pong [s] (the reference uses 1 s).
  double ping_interval_s = 1.0;
  // Lob datagram re-send period while waiting for the call-back [s] (reference: 2 s).
  double lob_retry_s = 2.0;
  // A TCP connect, or the VRPN cookie exchange after it, still under way after this long is
  // abandoned and retried [s]. So is, for a host name (not an IPv4 address), a lob whose call-back
  // has not come: the retry looks the name up again.
  double connect_timeout_s = 5.0;
  // A connection on which nothing arrives for this long is dropped and made again [s]: a server
  // that died without closing it (a crash, a pulled cable, a sleeping laptop) would otherwise hold
  // the client forever. After half of it in silence the client pings (every ping_interval_s); a
  // live server answers, so a quiet tracker is not taken for a dead server.
  double liveness_timeout_s = 10.0;
  // Wait before reconnecting after a failure or a dropped connection [s].
  double reconnect_delay_s = 1.0;
  // Offer a UDP data port in lob mode.
  bool udp_channel = true;
  // Largest accepted message from the server.
  std::uint32_t max_message_length = kDefaultMaxMessageLength;
  // Host name -> dotted IPv4 address, nullopt if unknown. Empty: getaddrinfo. It runs on a thread
  // of its own that Stop() does not wait for, so a DNS server that does not answer never holds up
  // Stop() (Unity's OnDisable), and may outlive the client: capture by value or shared_ptr, never
  // references to the caller's locals or to the client. A dotted address is used as is. Called
  // again before each reconnect; when that fails, the address found before is tried. nullopt:
  // the name has no address (host_unknown()); a throw: the lookup failed for now, tried again.
  std::function<std::optional<std::string>(const std::string& host)> resolve_host;
  void Check() const;
};

struct TrackerReport {
  int sensor = 0;
  Rigid3d transmitter_from_receiver;
  Timestamp time;  // header timestamp: when the server says the pose was measured
  bool via_udp = false;
};

class VrpnTrackerClient {
 public:
  using PoseCallback = std::function<void(const TrackerReport&)>;
  using MessageCallback = std::function<void(const ReceivedMessage&)>;

  explicit VrpnTrackerClient(const std::string& name, TrackerClientOptions options = {});
  ~VrpnTrackerClient();
  VrpnTrackerClient(const VrpnTrackerClient&) = delete;
  VrpnTrackerClient& operator=(const VrpnTrackerClient&) = delete;

  // Set before Poll()/Start().
  void SetPoseCallback(PoseCallback callback) { on_pose_ = std::move(callback); }
  // Every other message from our device name (text, pong, To_Room, button changes, ...).
  void SetMessageCallback(MessageCallback callback) { on_message_ = std::move(callback); }

  // Runs the connection: waits up to timeout_s for network events and handles them.
  void Poll(double timeout_s);
  // Background thread calling Poll until Stop().
  void Start();
  void Stop();

  // Queues the three static-information requests (To_Room, Unit_To_Sensor, Workspace).
  void RequestStaticInfo();

  bool connected() const { return connected_; }  // cookie exchange done
  bool pong_received() const { return pong_received_; }
  // The last look-up of the host name found no address, and none was found before: a mistyped or
  // unknown host, not a server that is down. Never for a dotted IPv4 address, nor for a look-up
  // that failed for now (EAI_AGAIN: the network or DNS server not up yet), which is retried.
  bool host_unknown() const { return host_unknown_; }
  bool udp_active() const { return udp_active_; }  // a report came over UDP
  std::uint64_t reports() const { return reports_; }
  std::uint64_t connections() const { return connections_; }
  std::uint64_t connect_attempts() const {
    return connect_attempts_;
  }  // TCP connects or lobs begun
  const VrpnName& name() const { return name_; }

 private:
  struct Impl;
  void Reset(const std::string& why);
  bool ResolveServer();  // false: not known yet (next_retry set)
  void BeginConnect();
  void OnTcpConnected();
  void HandleMessage(const ReceivedMessage& m);
  void FlushTcp();

  VrpnName name_;
  TrackerClientOptions options_;
  PoseCallback on_pose_;
  MessageCallback on_message_;
  std::unique_ptr<Impl> impl_;
  std::atomic<bool> connected_{false};
  std::atomic<bool> pong_received_{false};
  std::atomic<bool> host_unknown_{false};
  std::atomic<bool> udp_active_{false};
  std::atomic<std::uint64_t> reports_{0};
  std::atomic<std::uint64_t> connections_{0};
  std::atomic<std::uint64_t> connect_attempts_{0};
  std::thread thread_;
  std::atomic<bool> running_{false};
};

}  // namespace trackcal::vrpn
