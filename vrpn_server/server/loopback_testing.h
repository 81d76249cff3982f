// Test helpers shared by the tests that run a VrpnServer and clients over loopback.
#pragma once

#include <chrono>
#include <functional>
#include <thread>
#include <vector>

#include "vrpn_server/client/tracker_client.h"
#include "vrpn_server/server/server.h"

namespace trackcal::testing {

// A server on 127.0.0.1 at a port the kernel picks.
inline vrpn::ServerOptions LoopbackOptions() {
  vrpn::ServerOptions o;
  o.bind_address = "127.0.0.1";
  o.port = 0;
  return o;
}

// Polls the clients until pred() holds or timeout_s (generous: a loaded machine) passes. One
// client waits in its Poll; several are polled in turn without waiting (so none starves), with a
// short sleep between rounds; with none the loop sleeps instead of spinning.
inline bool PollUntil(const std::vector<vrpn::VrpnTrackerClient*>& clients,
                      const std::function<bool()>& pred, double timeout_s = 10.0) {
  const auto end = std::chrono::steady_clock::now() + std::chrono::duration<double>(timeout_s);
  while (std::chrono::steady_clock::now() < end) {
    if (pred()) return true;
    for (auto* c : clients) c->Poll(clients.size() > 1 ? 0.0 : 0.01);
    if (clients.size() > 1) std::this_thread::sleep_for(std::chrono::microseconds(200));
    if (clients.empty()) std::this_thread::sleep_for(std::chrono::milliseconds(2));
  }
  return pred();
}

}  // namespace trackcal::testing
