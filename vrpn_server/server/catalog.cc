#include "vrpn_server/server/catalog.h"

#include <stdexcept>

#include "vrpn_server/protocol/wire.h"

namespace trackcal::vrpn {
namespace {

void CheckName(const std::string& what, const std::string& name) {
  if (name.empty() || name.size() > kMaxNameLength || name.find('\0') != std::string::npos) {
    throw std::invalid_argument(what + ".name '" + name + "': must be 1 to 95 characters");
  }
}

}  // namespace

void TrackerSpec::Check() const {
  CheckName("TrackerSpec", name);
  if (num_sensors < 1 || num_sensors > 1024) {
    throw std::invalid_argument("TrackerSpec.num_sensors of '" + name + "': must be in [1, 1024]");
  }
  if (!sensor_from_unit.empty() && static_cast<int>(sensor_from_unit.size()) != num_sensors) {
    throw std::invalid_argument("TrackerSpec.sensor_from_unit of '" + name +
                                "': must be empty or have num_sensors entries");
  }
}

void ButtonSpec::Check() const {
  CheckName("ButtonSpec", name);
  if (num_buttons < 1 || num_buttons > 256) {
    throw std::invalid_argument("ButtonSpec.num_buttons of '" + name + "': must be in [1, 256]");
  }
}

ServerCatalog::ServerCatalog() : names_(std::make_shared<NameRegistry>()) {
  names_->AddSender(kControlSender);
  types_.pos_quat = names_->AddType(kPosQuatType);
  types_.velocity = names_->AddType(kVelocityType);
  types_.acceleration = names_->AddType(kAccelerationType);
  types_.to_room = names_->AddType(kToRoomType);
  types_.unit_to_sensor = names_->AddType(kUnitToSensorType);
  types_.request_to_room = names_->AddType(kRequestToRoomType);
  types_.request_unit_to_sensor = names_->AddType(kRequestUnitToSensorType);
  types_.workspace = names_->AddType(kWorkspaceType);
  types_.request_workspace = names_->AddType(kRequestWorkspaceType);
  types_.set_update_rate = names_->AddType(kSetUpdateRateType);
  types_.reset_origin = names_->AddType(kResetOriginType);
  types_.text = names_->AddType(kTextType);
  types_.ping = names_->AddType(kPingType);
  types_.pong = names_->AddType(kPongType);
  types_.button_change = names_->AddType(kButtonChangeType);
  types_.button_states = names_->AddType(kButtonStatesType);
}

int ServerCatalog::AddTracker(const TrackerSpec& spec) {
  spec.Check();
  if (FindTracker(spec.name)) {
    throw std::invalid_argument("TrackerSpec.name '" + spec.name + "': served twice");
  }
  trackers_.push_back(spec);
  tracker_senders_.push_back(names_->AddSender(spec.name));
  return static_cast<int>(trackers_.size() - 1);
}

int ServerCatalog::AddButton(const ButtonSpec& spec) {
  spec.Check();
  for (const auto& b : buttons_) {
    if (b.name == spec.name) {
      throw std::invalid_argument("ButtonSpec.name '" + spec.name + "': served twice");
    }
  }
  buttons_.push_back(spec);
  button_senders_.push_back(names_->AddSender(spec.name));
  return static_cast<int>(buttons_.size() - 1);
}

std::optional<int> ServerCatalog::FindTracker(std::string_view name) const {
  for (std::size_t i = 0; i < trackers_.size(); ++i) {
    if (trackers_[i].name == name) return static_cast<int>(i);
  }
  return std::nullopt;
}

bool ServerCatalog::Serves(std::string_view name) const {
  if (FindTracker(name)) return true;
  for (const auto& b : buttons_) {
    if (b.name == name) return true;
  }
  return false;
}

}  // namespace trackcal::vrpn
