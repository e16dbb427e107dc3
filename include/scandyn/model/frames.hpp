// scandyn/model/frames.hpp: finding a model's frames (ModelTpl::frames: every URDF
// link, merged fixed links and the root included) by name.
#pragma once

#include <string>
#include <vector>

#include "scandyn/model/load.hpp"

namespace scandyn {

// The index in model.frames of the frame named `name`. Throws ModelError naming it
// and listing the frames there are ("model 'iiwa': no frame 'tool'; frames: base,
// link_1, ...").
Index frame_index(const ModelTpl<double>& model, const std::string& name);

// The frames of a comma-separated list of names ("ee,link_3"), in its order
// (repeats allowed); each unknown name as in frame_index. An empty list throws.
std::vector<Index> parse_frame_list(const ModelTpl<double>& model, const std::string& list);

// The frames of the bodies' links, body 0 to nv - 1: the default selection (one
// frame per moving body, in DoF order).
std::vector<Index> body_frames(const ModelTpl<double>& model);

}  // namespace scandyn
