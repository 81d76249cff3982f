// Bindings of vrpn_server/client/tracker_client.h: a recorder that runs the C++ VRPN tracker client
// on its own thread and keeps every pose report, so Python can record live raw and corrected streams
// from a trackcal-server (or any VRPN server) for a later validation.
#include <pybind11/numpy.h>
#include <pybind11/stl.h>

#include <mutex>
#include <vector>

#include "python/src/bindings.h"
#include "vrpn_server/client/tracker_client.h"

namespace py = pybind11;

namespace trackcal::python {
namespace {

class TrackerRecorder {
 public:
  explicit TrackerRecorder(const std::string& name) : client_(name) {
    client_.SetPoseCallback([this](const vrpn::TrackerReport& r) {
      std::lock_guard<std::mutex> lock(mutex_);
      reports_.push_back(r);
    });
  }
  ~TrackerRecorder() { client_.Stop(); }

  void Start() { client_.Start(); }
  void Stop() {
    py::gil_scoped_release release;
    client_.Stop();
  }
  size_t Size() {
    std::lock_guard<std::mutex> lock(mutex_);
    return reports_.size();
  }
  // Moves the reports received so far out as arrays (time = server header time [s]).
  py::dict Take() {
    std::vector<vrpn::TrackerReport> reports;
    {
      std::lock_guard<std::mutex> lock(mutex_);
      reports.swap(reports_);
    }
    const py::ssize_t n = static_cast<py::ssize_t>(reports.size());
    py::array_t<double> time(n), positions({n, py::ssize_t{3}}), quats({n, py::ssize_t{4}});
    py::array_t<int> sensor(n);
    auto p = positions.mutable_unchecked<2>();
    auto q = quats.mutable_unchecked<2>();
    for (py::ssize_t i = 0; i < n; ++i) {
      const auto& r = reports[i];
      time.mutable_at(i) = r.time.Seconds();
      sensor.mutable_at(i) = r.sensor;
      for (int k = 0; k < 3; ++k) p(i, k) = r.transmitter_from_receiver.translation[k];
      double xyzw[4];
      QuaternionToXyzwArray(r.transmitter_from_receiver.rotation, xyzw);
      for (int k = 0; k < 4; ++k) q(i, k) = xyzw[k];
    }
    py::dict d;
    d["time"] = time;
    d["sensor"] = sensor;
    d["positions"] = positions;
    d["quaternions_xyzw"] = quats;
    return d;
  }
  bool connected() const { return client_.connected(); }
  bool pong_received() const { return client_.pong_received(); }
  bool host_unknown() const { return client_.host_unknown(); }
  std::string host() const { return client_.name().host; }

 private:
  vrpn::VrpnTrackerClient client_;
  std::mutex mutex_;
  std::vector<vrpn::TrackerReport> reports_;
};

}  // namespace

void BindVrpn(py::module_& m) {
  py::class_<TrackerRecorder>(
      m, "TrackerRecorder",
      "Records every pose report of a VRPN tracker ('Tracker0@tcp://host:port' or "
      "'Tracker0@host[:port]') on a background thread.")
      .def(py::init([](const std::string& name) {
             try {
               return std::make_unique<TrackerRecorder>(name);
             } catch (const std::invalid_argument& e) {
               throw py::value_error(e.what());
             }
           }),
           py::arg("name"))
      .def("start", &TrackerRecorder::Start, "Connects and starts recording.")
      .def("stop", &TrackerRecorder::Stop, "Stops the client thread (reports stay available).")
      .def("take", &TrackerRecorder::Take,
           "The reports received since the last take: time [s] (server header time), sensor "
           "(sensor number on the wire), positions (N, 3) [m], quaternions_xyzw (N, 4).")
      .def("__len__", &TrackerRecorder::Size)
      .def_property_readonly("connected", &TrackerRecorder::connected)
      .def_property_readonly("pong_received", &TrackerRecorder::pong_received)
      .def_property_readonly("host_unknown", &TrackerRecorder::host_unknown,
                             "The host name did not resolve to an address (a typo, or no DNS).")
      .def_property_readonly("host", &TrackerRecorder::host);
}

}  // namespace trackcal::python
