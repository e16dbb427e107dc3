// tests/cli/cli_test_util.hpp: what the command-line tests share: a fresh temporary
// directory per test, running `scandyn` in it with its output captured, and small
// file helpers.
#pragma once

#include <gtest/gtest.h>
#include <stdlib.h>
#include <sys/wait.h>

#include <algorithm>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <system_error>
#include <vector>

#include "test_util.hpp"

namespace scandyn::test::cli {

namespace fs = std::filesystem;

inline std::string read_text(const fs::path& p) {
  std::ifstream f(p, std::ios::binary);
  std::stringstream ss;
  ss << f.rdbuf();
  return ss.str();
}

inline void write_text(const fs::path& p, const std::string& text) {
  std::ofstream f(p, std::ios::binary);
  f << text;
}

// s as one single-quoted shell word.
inline std::string quote(const std::string& s) {
  std::string q = "'";
  for (char c : s) q += c == '\'' ? std::string("'\\''") : std::string(1, c);
  return q + "'";
}

struct Result {
  int code = -1;
  std::string out, err;
};

// A test with its own empty directory (removed afterwards), where `scandyn` runs.
class CliDirTest : public ::testing::Test {
 protected:
  void SetUp() override {
    std::string tmpl = (fs::temp_directory_path() / "scandyn_cli_XXXXXX").string();
    ASSERT_NE(::mkdtemp(&tmpl[0]), nullptr);
    dir_ = tmpl;
  }
  void TearDown() override {
    std::error_code ec;
    fs::remove_all(dir_, ec);
  }

  fs::path path(const std::string& name) const { return dir_ / name; }

  // Runs `env scandyn args` in the test directory (env: variable assignments or "").
  Result run(const std::string& args, const std::string& env = "") const { return run_program(cli_path(), args, env); }

  // Runs `env program args` in the test directory, its output captured.
  Result run_program(const std::string& program, const std::string& args, const std::string& env = "") const {
    const std::string cmd = "cd " + quote(dir_.string()) + " && " + env + " " + quote(program) + " " + args +
                            " >" + quote(path(".stdout").string()) + " 2>" + quote(path(".stderr").string());
    const int status = std::system(cmd.c_str());
    Result r;
    r.code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
    r.out = read_text(path(".stdout"));
    r.err = read_text(path(".stderr"));
    return r;
  }

  // Files in the test directory, hidden ones (temporary files) included, except
  // the captured stdout/stderr.
  std::vector<std::string> files() const {
    std::vector<std::string> names;
    for (const auto& e : fs::directory_iterator(dir_)) {
      const std::string n = e.path().filename().string();
      if (n != ".stdout" && n != ".stderr") names.push_back(n);
    }
    std::sort(names.begin(), names.end());
    return names;
  }

  fs::path dir_;
};

}  // namespace scandyn::test::cli
