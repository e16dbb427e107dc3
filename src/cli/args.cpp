// src/cli/args.cpp: flag parsing for the subcommands.
#include <algorithm>
#include <cstring>

#include "cli.hpp"

#include <cstdio>

#include "scandyn/model/load.hpp"

namespace scandyn::cli {

Args::Args(std::string command, int argc, char** argv, int first,
           const std::vector<std::string>& allowed)
    : command_(std::move(command)) {
  // --help anywhere wins over every other flag, a bad one included (exit 0)
  for (int k = first; k < argc; ++k) {
    if (std::strcmp(argv[k], "--help") == 0 || std::strcmp(argv[k], "-h") == 0) {
      help_ = true;
      return;
    }
  }
  for (int k = first; k < argc; ++k) {
    const std::string arg = argv[k];
    if (arg == "--help" || arg == "-h") {
      help_ = true;
      continue;
    }
    if (arg.compare(0, 2, "--") != 0 || arg.size() == 2)
      throw UsageError("unexpected argument '" + arg + "' to '" + command_ + "'");
    const std::size_t eq = arg.find('=');
    const std::string name = arg.substr(2, eq == std::string::npos ? std::string::npos : eq - 2);
    const bool known = std::find(allowed.begin(), allowed.end(), name) != allowed.end();
    if (!known) throw UsageError("unknown flag '--" + name + "' for '" + command_ + "'");
    if (values_.count(name)) throw UsageError("flag '--" + name + "' given more than once");
    std::string value;
    if (std::find(kSwitches.begin(), kSwitches.end(), name) != kSwitches.end()) {
      if (eq != std::string::npos) throw UsageError("flag '--" + name + "' takes no value");
      values_[name] = "1";
      continue;
    }
    if (eq != std::string::npos) {
      value = arg.substr(eq + 1);
    } else {
      if (k + 1 >= argc || std::strncmp(argv[k + 1], "--", 2) == 0)
        throw UsageError("flag '--" + name + "' needs a value");
      value = argv[++k];
    }
    if (value.empty()) throw UsageError("flag '--" + name + "' has an empty value");
    values_[name] = value;
  }
}

const std::string& Args::required(const std::string& name) const {
  const auto it = values_.find(name);
  if (it == values_.end()) throw UsageError("'" + command_ + "' needs --" + name);
  return it->second;
}

std::string Args::get(const std::string& name, const std::string& fallback) const {
  const auto it = values_.find(name);
  return it == values_.end() ? fallback : it->second;
}

Model load_cli_model(const Args& args) {
  BuildOptions options;
  std::vector<std::string> warnings;
  options.require_physical_inertia = !args.has("allow-nonphysical-inertia");
  options.floating_base = args.has("floating-base");
  options.warnings = &warnings;
  Model model = load_model(args.required("model"), options);
  for (const auto& w : warnings) std::fprintf(stderr, "scandyn: warning: %s\n", w.c_str());
  return model;
}

}  // namespace scandyn::cli
