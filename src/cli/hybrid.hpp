// src/cli/hybrid.hpp: the command line's hybrid dynamics (`eval --algo hybrid`,
// `bench --algo hybrid`) on the library's HybridDynamics engine, and eval on models
// with closed loops.
#pragma once

#include <string>
#include <vector>

#include "cli.hpp"
#include "scandyn/algorithm/loops.hpp"

namespace scandyn::cli {

// --prescribed LIST: comma-separated DoF indices (0, 3, 5) or joint names, mixed
// freely, as the model's prescribed mask (nv entries, 1 = the DoF's acceleration is
// given). "" prescribes none. Throws UsageError naming an unknown joint, an index
// out of range, an empty item or a DoF listed twice.
// flag names the flag in messages (--actuated takes the same list).
std::vector<unsigned char> parse_prescribed(const std::string& list, const Model& model,
                                            const std::string& flag = "prescribed");

// `scandyn eval --algo hybrid --prescribed LIST ...` (run_eval hands it over).
int run_eval_hybrid(const Args& args);

// `scandyn eval` on a model with closed loops: --loops FILE, or a generator that
// carries loops (run_eval hands it over; src/cli/eval_loops.cpp).
int run_eval_loops(const Args& args);

// The loops of a command: the generator's (fivebar, fourbar, cloth:K:N) and those of
// --loops FILE (DataError naming the file, loop and key); eval_loops.cpp.
LoopSet load_cli_loops(const Args& args, const Model& model);

}  // namespace scandyn::cli
