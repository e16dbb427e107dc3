// src/cli/cli.hpp: pieces shared by the subcommands of `scandyn`.
#pragma once

#include <map>
#include <stdexcept>
#include <string>
#include <vector>

#include "scandyn/model/model.hpp"

namespace scandyn::io {}

namespace scandyn::cli {

// The file formats and output files (scandyn/io/*.hpp) are the command line's own.
using namespace scandyn::io;

// Exit codes.
constexpr int kExitOk = 0;
constexpr int kExitData = 1;   // bad input data, model, file system or numerics
constexpr int kExitUsage = 2;  // bad command line

// A bad command line: printed as one line, exit code 2, by default followed by a
// pointer to the command's --help.
class UsageError : public std::runtime_error {
 public:
  explicit UsageError(const std::string& what, bool hint_help = true)
      : std::runtime_error(what), hint_help(hint_help) {}
  bool hint_help;
};

// Bad input data or a failed computation: printed as one line, exit code 1.
class DataError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

// The flags of one subcommand: "--name value" or "--name=value"; "--help" and the
// switches (flags without a value, kSwitches) alone.
class Args {
 public:
  // Parses argv[first, argc) for subcommand command, accepting only the given
  // flag names (without "--"). Throws UsageError for an unknown or repeated
  // flag, a missing value or a stray argument.
  Args(std::string command, int argc, char** argv, int first,
       const std::vector<std::string>& allowed);

  const std::string& command() const { return command_; }
  bool help() const { return help_; }
  bool has(const std::string& name) const { return values_.count(name) != 0; }
  // The value of a required flag; throws UsageError if it was not given.
  const std::string& required(const std::string& name) const;
  std::string get(const std::string& name, const std::string& fallback) const;

 private:
  std::string command_;
  bool help_ = false;
  std::map<std::string, std::string> values_;
};

// Flags that take no value.
inline const std::vector<std::string> kSwitches = {"allow-nonphysical-inertia", "floating-base", "print-loops", "contacts"};

// Loads --model, honouring --allow-nonphysical-inertia (waived inertia checks are
// printed to stderr as warnings). Throws ModelError.
Model load_cli_model(const Args& args);

// The subcommands; each returns the exit code and throws UsageError, DataError,
// CsvError or ModelError on failure.
int run_info(const Args& args);
int run_eval(const Args& args);
int run_bench(const Args& args);
int run_rollout(const Args& args);

}  // namespace scandyn::cli
