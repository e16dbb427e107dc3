// src/model/urdf.cpp: URDF text -> RawTree with urdfdom; file and spec entry points.
//
// urdfdom reports problems through console_bridge logging: sometimes it returns null,
// sometimes (a broken <inertial>) it logs an error and returns a model anyway. We
// capture every error it logs while parsing and treat any of them as failure, so
// the ModelError carries urdfdom's own words, prefixed with the file name.
#include <console_bridge/console.h>
#include <urdf_parser/urdf_parser.h>

#include <cstdio>
#include <mutex>
#include <string>
#include <vector>

#include "scandyn/io/limits.hpp"
#include "scandyn/model/load.hpp"

namespace scandyn {
namespace {

// Collects urdfdom's error messages while installed; restores the previous
// handler and log level when destroyed. console_bridge state is global, so one
// parse at a time (parse_mutex).
class CaptureErrors : public console_bridge::OutputHandler {
 public:
  CaptureErrors() : previous_(console_bridge::getOutputHandler()), level_(console_bridge::getLogLevel()) {
    console_bridge::useOutputHandler(this);
    console_bridge::setLogLevel(console_bridge::CONSOLE_BRIDGE_LOG_ERROR);
  }
  ~CaptureErrors() override {
    console_bridge::setLogLevel(level_);
    console_bridge::useOutputHandler(previous_);
  }
  CaptureErrors(const CaptureErrors&) = delete;
  CaptureErrors& operator=(const CaptureErrors&) = delete;

  void log(const std::string& text, console_bridge::LogLevel level, const char*, int) override {
    if (level >= console_bridge::CONSOLE_BRIDGE_LOG_ERROR) errors.push_back(text);
  }

  // The errors as one line: urdfdom's generic follow-ups ("joint xml is not
  // initialized correctly") dropped when a specific message exists.
  std::string message() const {
    std::vector<std::string> kept;
    for (const auto& e : errors)
      if (e.find("is not initialized correctly") == std::string::npos) kept.push_back(e);
    if (kept.empty()) kept = errors;
    std::string s;
    for (const auto& e : kept) {
      if (!s.empty()) s += "; ";
      s += e;
    }
    for (char& c : s)
      if (c == '\n' || c == '\r') c = ' ';
    return s;
  }

  std::vector<std::string> errors;

 private:
  console_bridge::OutputHandler* previous_;
  console_bridge::LogLevel level_;
};

std::mutex parse_mutex;

Vec3<double> vec(const urdf::Vector3& v) { return {v.x, v.y, v.z}; }
RawQuat quat(const urdf::Rotation& r) {
  RawQuat q;
  r.getQuaternion(q.x, q.y, q.z, q.w);
  return q;
}

RawJointType joint_type(int t, std::string& name) {
  switch (t) {
    case urdf::Joint::REVOLUTE: name = "revolute"; return RawJointType::Revolute;
    case urdf::Joint::CONTINUOUS: name = "continuous"; return RawJointType::Continuous;
    case urdf::Joint::PRISMATIC: name = "prismatic"; return RawJointType::Prismatic;
    case urdf::Joint::FIXED: name = "fixed"; return RawJointType::Fixed;
    case urdf::Joint::FLOATING: name = "floating"; return RawJointType::Floating;
    case urdf::Joint::PLANAR: name = "planar"; return RawJointType::Planar;
    default: name = "unknown"; return RawJointType::Unknown;
  }
}

}  // namespace

RawTree parse_urdf(const std::string& xml, const std::string& source) {
  // bounded before parsing: tinyxml recurses once per nesting level (50,000 levels
  // overflow the stack), and a URDF needs 4 (robot, link, inertial, origin)
  if (xml.size() > limits::kMaxUrdfBytes)
    throw ModelError(source + ": the URDF text has " + std::to_string(xml.size()) + " bytes; at most " +
                     std::to_string(limits::kMaxUrdfBytes) + " are read");
  if (xml_depth(xml, limits::kMaxXmlDepth) > limits::kMaxXmlDepth)
    throw ModelError(source + ": XML elements nested deeper than " + std::to_string(limits::kMaxXmlDepth) +
                     " levels (a URDF needs 4)");
  if (xml.find('\0') != std::string::npos)
    throw ModelError(source + ": the URDF text contains a NUL byte at offset " + std::to_string(xml.find('\0')));
  urdf::ModelInterfaceSharedPtr model;
  std::string errors;
  {
    std::lock_guard<std::mutex> lock(parse_mutex);
    CaptureErrors capture;
    try {
      model = urdf::parseURDF(xml);
    } catch (const std::exception& e) {
      capture.errors.push_back(e.what());
    }
    errors = capture.message();
  }
  if (!errors.empty()) throw ModelError(source + ": " + errors);
  if (!model) throw ModelError(source + ": not a valid URDF (urdfdom gave no reason)");

  RawTree t;
  t.name = model->getName();
  t.source = source;
  t.links.reserve(model->links_.size());
  for (const auto& kv : model->links_) {
    const urdf::Link& l = *kv.second;
    RawLink r;
    r.name = l.name;
    if (l.inertial) {
      const urdf::Inertial& in = *l.inertial;
      r.has_inertial = true;
      r.mass = in.mass;
      r.com_xyz = vec(in.origin.position);
      r.com_has_quat = true;
      r.com_quat = quat(in.origin.rotation);
      r.inertia = {in.ixx, in.iyy, in.izz, in.ixy, in.ixz, in.iyz};
    }
    t.links.push_back(std::move(r));
  }
  t.joints.reserve(model->joints_.size());
  for (const auto& kv : model->joints_) {
    const urdf::Joint& j = *kv.second;
    RawJoint r;
    r.name = j.name;
    r.type = joint_type(j.type, r.type_name);
    r.parent = j.parent_link_name;
    r.child = j.child_link_name;
    r.xyz = vec(j.parent_to_joint_origin_transform.position);
    r.has_quat = true;
    r.quat = quat(j.parent_to_joint_origin_transform.rotation);
    r.axis = vec(j.axis);
    if (j.limits && (j.type == urdf::Joint::REVOLUTE || j.type == urdf::Joint::PRISMATIC)) {
      r.lower = j.limits->lower;
      r.upper = j.limits->upper;
    }
    t.joints.push_back(std::move(r));
  }
  return t;
}

Model load_urdf(const std::string& path, const BuildOptions& options) {
  std::string text;
  try {
    text = read_regular_file(path, limits::kMaxUrdfBytes, "URDF file");
  } catch (const InputError& e) {
    throw ModelError(e.what());
  }
  return build_model(parse_urdf(text, printable(path)), options);
}

Model load_model(const std::string& path_or_spec, const BuildOptions& options) {
  if (is_generator_spec(path_or_spec)) return make_generated(path_or_spec, options);
  return load_urdf(find_model_file(path_or_spec), options);
}

}  // namespace scandyn
