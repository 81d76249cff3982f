// What a server serves: tracker and button devices by name, and the local sender/type numbering
// every connection describes to its peer. Built once before the server starts, then read-only.

#pragma once

#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "core/pose.h"
#include "vrpn_server/protocol/connection.h"
#include "vrpn_server/protocol/payloads.h"

namespace trackcal::vrpn {

struct TrackerSpec {
  // Device (sender) name clients ask for, e.g. "Tracker0" in "Tracker0@host".
  std::string name;
  // Number of sensors (stations); Unit_To_Sensor answers one message per sensor.
  int num_sensors = 1;
  // Answer to Request_Tracker_To_Room (information only; clients do not apply it). Identity by
  // default; the reference's compiled-in (0, 0, -0.28) is a desktop-Phantom leftover.
  Rigid3d room_from_tracker;
  // Answer to Request_Unit_To_Sensor, one per sensor (identity when empty).
  std::vector<Rigid3d> sensor_from_unit;
  // Answer to Request_Tracker_Workspace.
  Workspace workspace;
  void Check() const;  // throws std::invalid_argument naming the field
};

struct ButtonSpec {
  // Device (sender) name, e.g. "Stylus0".
  std::string name;
  // Number of buttons; vrpn_Button States lists all of them.
  int num_buttons = 1;
  void Check() const;
};

// Local type ids, registered in the reference's order. The ids are 4 lower than the reference's
// (Pos_Quat is 0 here, 4 in capture 01, which first registers the four VRPN_Connection_* types
// we do not describe); peers translate ids by name, so they need not match.
struct TypeIds {
  std::int32_t pos_quat, velocity, acceleration, to_room, unit_to_sensor, request_to_room,
      request_unit_to_sensor, workspace, request_workspace, set_update_rate, reset_origin, text,
      ping, pong, button_change, button_states;
};

class ServerCatalog {
 public:
  ServerCatalog();
  // Returns the tracker index. Throws std::invalid_argument for a bad spec or a duplicate tracker.
  int AddTracker(const TrackerSpec& spec);
  // Returns the button device index. A button may share its name with a tracker.
  int AddButton(const ButtonSpec& spec);

  const std::vector<TrackerSpec>& trackers() const { return trackers_; }
  const std::vector<ButtonSpec>& buttons() const { return buttons_; }
  std::int32_t tracker_sender(int tracker) const { return tracker_senders_.at(tracker); }
  std::int32_t button_sender(int button) const { return button_senders_.at(button); }
  std::optional<int> FindTracker(std::string_view name) const;
  // True when name is a served device (tracker or button): only those get pongs.
  bool Serves(std::string_view name) const;
  const TypeIds& types() const { return types_; }
  std::shared_ptr<const NameRegistry> names() const { return names_; }

 private:
  std::shared_ptr<NameRegistry> names_;
  TypeIds types_{};
  std::vector<TrackerSpec> trackers_;
  std::vector<ButtonSpec> buttons_;
  std::vector<std::int32_t> tracker_senders_;
  std::vector<std::int32_t> button_senders_;
};

}  // namespace trackcal::vrpn
