// src/cli/info.cpp: `scandyn info`, a model's summary and DoF order.
#include "scandyn/algorithm/loops.hpp"
#include <algorithm>
#include <cstdio>

#include "cli.hpp"
#include "scandyn/cuda/device.hpp"
#include "scandyn/model/load.hpp"

namespace scandyn::cli {
namespace {

std::string format_g(double x) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%g", x == 0 ? 0.0 : x);  // no "-0"
  return buf;
}

std::string format_vec3(const Vec3<double>& v) {
  return format_g(v.x) + " " + format_g(v.y) + " " + format_g(v.z);
}

// Prints rows as columns separated by two spaces, each as wide as its widest cell.
void print_table(const std::vector<std::vector<std::string>>& rows) {
  std::vector<std::size_t> width;
  for (const auto& r : rows) {
    width.resize(std::max(width.size(), r.size()), 0);
    for (std::size_t c = 0; c < r.size(); ++c) width[c] = std::max(width[c], r[c].size());
  }
  std::string line;
  for (const auto& r : rows) {
    line.clear();
    for (std::size_t c = 0; c < r.size(); ++c) {
      line += r[c];
      if (c + 1 < r.size()) line.append(width[c] - r[c].size() + 2, ' ');
    }
    std::puts(line.c_str());
  }
}

// One "cuda" row per usable device ("0: NVIDIA H100 ... (sm_90, ...)"), or one row
// saying why there is none.
void add_cuda_rows(std::vector<std::vector<std::string>>& rows) {
  const cuda::Result<int> count = cuda::device_count();
  if (!count) {
    rows.push_back({"cuda", count.error});
    return;
  }
  if (count.value == 0) rows.push_back({"cuda", "no usable CUDA device: the CUDA runtime reports 0 devices"});
  for (int d = 0; d < count.value; ++d) {
    const cuda::Result<cuda::DeviceInfo> info = cuda::device_info(d);
    rows.push_back({"cuda", info ? cuda::describe(info.value) : info.error});
  }
}

// The closed-loop solvers this command has (scene key "loop_solver"; docs/loops.md).
const char* loop_solvers() {
#if SCANDYN_CLI_SPARSE_LOOPS
  return "dense, iterative, sparse (CHOLMOD)";
#else
  return "dense, iterative (no sparse loop solver: built without SuiteSparse CHOLMOD)";
#endif
}

}  // namespace

int run_info(const Args& args) {
  const Model model = load_cli_model(args);
  if (args.has("print-loops")) {  // the generator's loops as a loop file
    std::fputs(loops_json(generator_loops(args.required("model"), model)).c_str(), stdout);
    return kExitOk;
  }
  std::vector<std::vector<std::string>> summary = {
      {"model", model.name},
      {"source", model.source},
      {"nv", std::to_string(model.nv())},
      {"nq", std::to_string(model.nq())},
      {"base", model.floating_base() ? "floating" : "fixed"},
      {"root", model.root_link},
      {"gravity", format_vec3(model.gravity)},
  };
  add_cuda_rows(summary);
  summary.push_back({"loops", loop_solvers()});
  print_table(summary);
  std::puts("");
  // one row per body; with multi-DoF joints also where each joint's entries start
  // in q and in qd
  const bool multi = model.multi_dof();
  std::vector<std::vector<std::string>> rows = {{"index", "joint", "type", "parent", "child", "axis"}};
  if (multi) rows[0].insert(rows[0].begin() + 1, {"q", "v"});
  for (Index i = 0; i < model.nbodies(); ++i) {
    const Body<double>& b = model.bodies[static_cast<std::size_t>(i)];
    const bool one = b.type == JointType::Revolute || b.type == JointType::Prismatic;
    rows.push_back({std::to_string(i), model.joint_names[static_cast<std::size_t>(i)],
                    b.type == JointType::Revolute    ? "revolute"
                    : b.type == JointType::Prismatic ? "prismatic"
                    : b.type == JointType::Spherical ? "spherical"
                                                     : "free",
                    std::to_string(b.parent), model.link_names[static_cast<std::size_t>(i)],
                    one ? format_vec3(b.axis) : "-"});
    if (multi) rows.back().insert(rows.back().begin() + 1, {std::to_string(b.idx_q), std::to_string(b.idx_v)});
  }
  print_table(rows);
  // the frames (every URDF link): the names --frames takes, the body carrying each
  // (-1 = base) and its origin in that body's frame
  std::puts("");
  std::vector<std::vector<std::string>> frames = {{"frame", "name", "body", "origin"}};
  for (std::size_t k = 0; k < model.frames.size(); ++k)
    frames.push_back({std::to_string(k), model.frame_names[k], std::to_string(model.frames[k].body),
                      format_vec3(model.frames[k].X.inverse().r)});
  print_table(frames);
  return kExitOk;
}

}  // namespace scandyn::cli
