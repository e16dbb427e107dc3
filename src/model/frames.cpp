// src/model/frames.cpp: frames by name (scandyn/model/frames.hpp).
#include "scandyn/model/frames.hpp"

namespace scandyn {

Index frame_index(const ModelTpl<double>& model, const std::string& name) {
  for (std::size_t k = 0; k < model.frame_names.size(); ++k)
    if (model.frame_names[k] == name) return static_cast<Index>(k);
  // the names there are, up to a readable number
  constexpr std::size_t kListed = 64;
  std::string known;
  for (std::size_t k = 0; k < model.frame_names.size() && k < kListed; ++k)
    known += (k ? ", " : "") + model.frame_names[k];
  if (model.frame_names.size() > kListed)
    known += ", ... (" + std::to_string(model.frame_names.size()) + " frames; `scandyn info` lists them all)";
  throw ModelError("model '" + model.name + "': no frame '" + name + "'; frames (URDF links): " + known);
}

std::vector<Index> parse_frame_list(const ModelTpl<double>& model, const std::string& list) {
  std::vector<Index> frames;
  std::size_t start = 0;
  for (;;) {
    const std::size_t comma = list.find(',', start);
    const std::string item = list.substr(start, comma == std::string::npos ? std::string::npos : comma - start);
    if (item.empty()) throw ModelError("frame list '" + list + "' has an empty name (expected names separated by commas)");
    frames.push_back(frame_index(model, item));
    if (comma == std::string::npos) break;
    start = comma + 1;
  }
  return frames;
}

std::vector<Index> body_frames(const ModelTpl<double>& model) {
  std::vector<Index> body_frame(static_cast<std::size_t>(model.nv()), -1);
  for (std::size_t k = 0; k < model.frames.size(); ++k) {
    const FramePlacement<double>& f = model.frames[k];
    // the body's own link: the first frame on it at its origin (merged links come after it)
    if (f.body >= 0 && body_frame[static_cast<std::size_t>(f.body)] < 0) body_frame[static_cast<std::size_t>(f.body)] = static_cast<Index>(k);
  }
  return body_frame;
}

}  // namespace scandyn
