// The event-driven VRPN server core: one network thread around epoll, no polling loop.
//
// - TCP listener (SO_REUSEADDR, large backlog, TCP_NODELAY on every connection) and the UDP "lob"
//   listener on the same port; a lob datagram makes the server connect back (non-blocking connect)
//   to the client's TCP port.
// - Every connection is an independent ServerSession with a bounded output buffer: a client that
//   stops reading is dropped when its buffer overflows, it never blocks the others.
// - On lob connections the server opens a UDP socket, announces it, and sends low-latency messages
//   (Pos_Quat) over UDP once the client has described its own UDP port.
// - Devices publish from their own threads (Publish* are thread-safe and never block on the
//   network): if the network thread is idle the publishing thread fans the report out itself
//   (saving a thread wake-up); otherwise the report goes through a mutex-protected queue and an
//   eventfd wakes the loop. Either way each report is encoded once, written to every client, and
//   reports keep their order.
// - Exposure: bind address, and an allow-list of client networks checked for accepted connections,
//   lob datagrams and call-back targets.

#pragma once

#include <sys/socket.h>

#include <atomic>
#include <chrono>
#include <cstdint>
#include <memory>
#include <mutex>
#include <span>
#include <string>
#include <thread>
#include <vector>

#include "core/pose.h"
#include "vrpn_server/protocol/payloads.h"
#include "vrpn_server/protocol/wire.h"
#include "vrpn_server/server/catalog.h"
#include "vrpn_server/server/server_session.h"

namespace trackcal::vrpn {

struct ServerOptions {
  // IPv4 address to bind the TCP and UDP listeners to ("0.0.0.0" = all interfaces).
  std::string bind_address = "0.0.0.0";
  // TCP and UDP port; 0 picks a free port (tests), see VrpnServer::port().
  int port = kDefaultPort;
  // Allowed client networks as CIDR ("192.168.1.0/24"); empty allows everyone, like VRPN.
  std::vector<std::string> allow;
  // Connections beyond this are refused (the reference limit is 256 endpoints).
  int max_clients = 256;
  // Per-client bytes waiting to be written; a client that lets more pile up is dropped.
  std::size_t max_output_bytes = 1 << 20;
  // Bytes waiting to be written to all clients together; past it the client with the most waiting
  // is dropped (and the next, until the total is under it). Half-open or non-reading clients each
  // holding max_output_bytes came to 256 MiB at max_clients 256; clients that read hold next to
  // nothing. Below max_output_bytes it is the lower per-client limit too.
  std::size_t max_total_output_bytes = 64 << 20;
  // Largest accepted message from a client (header length field); larger closes that client.
  std::uint32_t max_message_length = kDefaultMaxMessageLength;
  // Send Pos_Quat over UDP to lob clients that describe a UDP port.
  bool udp_data_channel = true;
  // TCP listen backlog (the reference uses 1, which serialises connection bursts).
  int listen_backlog = 1024;
  // A connection that has not completed its cookie exchange (or call-back connect) in this time
  // is dropped [s].
  double handshake_timeout_s = 10.0;
  // A client whose host vanished without closing (crash, power, network) is dropped after about
  // this long [s]: TCP keepalive probes and a limit on unacknowledged data. Without it a lob
  // client, idle on TCP, would keep its slot and its UDP stream for ever. 0 disables.
  double dead_client_timeout_s = 30.0;
  // A client that has sent part of a message and not the rest for this long is closed [s]: it holds
  // a slot without being served (and, at 64000 bytes a message, server memory). VRPN peers write
  // every message whole (the reference's vrpn_noint_block_write loops until all of it is written),
  // so the rest is already in the client's kernel even while the client program is busy; only a
  // network that loses the segment and its retransmissions (Linux: 0.2, 0.4, 0.8... s) holds it
  // up. Counted from the message's first byte, so a client trickling a byte at a time cannot
  // stretch it.
  double incomplete_message_timeout_s = 10.0;
  // A client that takes none of the bytes waiting for it for this long is dropped [s], however
  // few they are: one that stops reading while little is published would otherwise keep its slot
  // until max_output_bytes overflows, hours later at a tracker's rate, or never. A client program
  // busy for a few seconds is not dropped: its kernel keeps taking the stream (128 kB or more of
  // receive buffer, 10 s or more of a Fastrak's reports over TCP; a lob client's reports go over
  // UDP and do not wait), and only then does this clock start.
  double unread_output_timeout_s = 30.0;
  // With max_clients reached, a new client takes the place of a served connection that has been
  // stalled (one of the two above) for at least this long [s]. A message in flight completes
  // within a round trip (under a millisecond on a LAN; a lost segment is sent again after Linux's
  // 200 ms minimum RTO), and a client that reads leaves no output untaken for a second unless
  // its kernel's receive buffer is full: a client being served is not taken for a stalled one.
  double min_stall_to_evict_s = 1.0;
  // Refused or ignored connections, datagrams and call-backs are logged up to 100 lines per window
  // of this length [s]; the rest are counted and the count is logged when the window ends, so
  // a flood cannot fill the log, and refusals days later are still logged. Connection lines
  // (connected, closed, and what a client did wrong) have a cap of their own, the same way.
  double refusal_log_window_s = 60.0;
  // Real-time (SCHED_FIFO) priority for the network thread, 1..99; 0 keeps the normal scheduler.
  // Keeps client processes on the same host from preempting a fan-out halfway; needs
  // CAP_SYS_NICE (a warning is logged and the server runs normally without it).
  int realtime_priority = 0;
  // A device thread publishing while the network thread is idle sends to the clients itself
  // (never waiting for the network thread); false always hands reports to the network thread.
  // Ignored with a realtime_priority: the real-time network thread then does every fan-out.
  bool direct_fanout = true;
  void Check() const;  // throws std::invalid_argument naming the field
};

struct ServerStats {
  int clients = 0;                    // connections currently open
  std::uint64_t connections_total = 0;
  std::uint64_t refused = 0;          // allow-list, client limit, bad lob requests, strangers'
                                      // datagrams to a client's data port
  std::uint64_t dropped_slow = 0;     // closed because the output buffer overflowed, the client
                                      // took none of it for unread_output_timeout_s, or the kernel
                                      // timed it out (dead_client_timeout_s: not reading, or gone)
  std::uint64_t closed_protocol = 0;  // closed for a bad cookie or length field, or a message left
                                      // incomplete for incomplete_message_timeout_s
  std::uint64_t evicted = 0;          // closed, stalled, to make room for a new client
  std::uint64_t dropped_over_total = 0;  // closed with the most output waiting while all clients'
                                         // together passed max_total_output_bytes
  std::uint64_t reports_published = 0;
  std::uint64_t udp_send_failures = 0;
};

// One Pos_Quat to publish: tracker (catalog index), sensor, pose and header timestamp.
struct PoseUpdate {
  int tracker = 0;
  int sensor = 0;
  Rigid3d transmitter_from_receiver;
  Timestamp time;
};

class VrpnServer {
 public:
  // `log` may be called from the network thread and from publishing threads: it must be
  // thread-safe (the default, LogToStderr, is).
  VrpnServer(std::shared_ptr<const ServerCatalog> catalog, ServerOptions options,
             LogFunction log = nullptr);
  ~VrpnServer();
  VrpnServer(const VrpnServer&) = delete;
  VrpnServer& operator=(const VrpnServer&) = delete;

  // Binds the listeners (throws std::runtime_error naming address and port on failure) and starts
  // the network thread.
  void Start();
  // Stops the network thread and closes every connection. Idempotent.
  void Stop();
  // The bound port (useful with options.port = 0).
  int port() const { return port_; }

  // Thread-safe: queue a report for every client. Pos_Quat with the header timestamp `time`.
  void PublishPose(int tracker, int sensor, const Rigid3d& transmitter_from_receiver, Timestamp time);
  // Thread-safe: several reports that arrived together (the records of one serial read, raw and
  // corrected names of one record). They are fanned out together: each is encoded once, and every
  // client gets all of them in one send() (lob clients: one datagram), instead of one system call
  // per report and client. Throws std::invalid_argument for an unknown tracker (nothing is sent).
  void PublishPoses(std::span<const PoseUpdate> poses);
  // Thread-safe: a text message from a tracker's name to every client (reliable channel).
  void PublishText(int tracker, TextSeverity severity, std::string text);
  // Thread-safe: a button change; new clients get the current states on connect.
  void PublishButton(int button, int index, bool pressed, Timestamp time);

  ServerStats stats() const;
  // Server-side latency of every report batch since the last call [us]: from the first report's
  // hand-over (Publish*) to the last client's send() returning. Kept for at most 1e6 batches.
  std::vector<float> TakeFanoutMicros();
  // CPU time the network thread has used [s] (for the idle-CPU benchmark); 0 when not running.
  double NetworkThreadCpuSeconds() const;

 private:
  struct Endpoint;
  struct Event;
  struct Impl;
  void Push(Event event);
  // After events were queued: fan out from this thread if the network thread is idle, else wake it.
  void Kick(bool queue_was_empty);
  void Run();
  void HandleAccept();
  // True when a new client fits under max_clients, after closing, if need be, the connection that
  // has waited longest for its handshake, or else the one that has been stalled longest (part of
  // a message sent, or output not taken, for at least min_stall_to_evict_s): connections that are
  // not being served (a port scanner, a flood of idle connects, clients stuck halfway through a
  // message or not reading) cannot lock new clients out until their timeouts. A client that
  // finished its handshake and is not stalled is never closed to make room.
  bool RoomForNewClient();
  // Past max_total_output_bytes waiting for all clients, drops the clients with the most until the
  // total is under it again.
  void LimitTotalOutput();
  // Whether a refusal may be logged now (ServerOptions::refusal_log_window_s).
  bool RefusalLogAllowed();
  // Whether a connection line (connected, closed, a client's misbehaviour) may be logged now.
  bool ConnectionLogAllowed();
  // Logs the counts of lines the limiters left out in windows that have ended.
  void ReportSuppressedLines();
  // When the network thread must next wake: the earliest handshake deadline, stall timeout,
  // accept retry or report of suppressed lines (time_point::max() for none).
  std::chrono::steady_clock::time_point NextWakeUp() const;
  // Wakes the network thread (from a device thread that started a timer it must watch).
  void WakeLoop();
  // Puts the TCP listener in or out of the epoll set (out while accept() lacks resources).
  void SetAccepting(bool on);
  void DetectDeadClient(int fd);  // options_.dead_client_timeout_s on a client socket
  void HandleLob();
  // Reads the errors the kernel queued on the shared UDP socket for datagrams sent from it (ICMP):
  // a client whose UDP port is unreachable gets its reports over TCP from then on (logged once).
  void HandleUdpErrors();
  // Sends datagrams from the shared UDP socket (sendmmsg), owners[k] the endpoint of headers[k];
  // a send that fails is sent again once after HandleUdpErrors, as the failure may be another
  // datagram's ICMP error (the datagrams of a client that moved to TCP then go over TCP).
  void SendDatagrams(std::span<mmsghdr> headers, std::span<const std::uint64_t> owners);
  void HandleEndpoint(std::uint64_t id, std::uint32_t events, bool udp);
  void OnConnected(Endpoint& e);
  void StartSession(Endpoint& e);
  void Flush(Endpoint& e);
  enum class LineKind { kConnection, kRefusal, kNone };
  // Logs "closed <client>: why", within the cap of the lines of `kind` (kNone: not at all).
  void Close(std::uint64_t id, const std::string& why, LineKind kind = LineKind::kConnection);
  // Closes a client whose read() or send() failed with `err` ("read", "write": `op`).
  void CloseOnSocketError(std::uint64_t id, const char* op, int err);
  void DrainEvents();
  void CheckDeadlines();
  void UpdateInterest(Endpoint& e);
  void Log(const std::string& line);

  std::shared_ptr<const ServerCatalog> catalog_;
  ServerOptions options_;
  LogFunction log_;
  int port_ = 0;

  int epoll_fd_ = -1;
  int tcp_fd_ = -1;
  int udp_fd_ = -1;
  int event_fd_ = -1;
  std::thread thread_;
  std::atomic<bool> running_{false};

  std::unique_ptr<Impl> impl_;

  mutable std::mutex stats_mutex_;
  ServerStats stats_;
};

// Writes "<UTC time> trackcal-server: line" to stderr, `line` through PrintableForLog. Never
// blocks: the line is queued for a writer thread (the time is taken now), so a stderr nobody reads
// (a terminal paused with Ctrl-S, a stalled pipe) cannot stall the network thread; past 1 MiB
// queued, lines are dropped and their count is logged when stderr takes lines again.
void LogToStderr(const std::string& line);
// Waits until the lines queued by LogToStderr are written, at most `timeout`; false if they were
// not (stderr is not read). Call it before exiting and before writing to stderr directly.
bool FlushStderrLog(std::chrono::milliseconds timeout);

}  // namespace trackcal::vrpn
