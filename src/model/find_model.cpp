// src/model/find_model.cpp: where a model file named on the command line, in a
// scene or by the library's caller is found.
#include <sys/stat.h>

#include <cstdlib>

#include "scandyn/model/load.hpp"

#ifndef SCANDYN_SOURCE_MODELS_DIR
#define SCANDYN_SOURCE_MODELS_DIR ""
#endif
#ifndef SCANDYN_INSTALL_MODELS_DIR
#define SCANDYN_INSTALL_MODELS_DIR ""
#endif

namespace scandyn {
namespace {

bool is_file(const std::string& path) {
  struct stat st {};
  return ::stat(path.c_str(), &st) == 0 && S_ISREG(st.st_mode);
}

}  // namespace

std::vector<std::string> model_search_dirs() {
  std::vector<std::string> dirs;
  if (const char* env = std::getenv("SCANDYN_MODELS_DIR"); env && *env) dirs.emplace_back(env);
  for (const char* d : {SCANDYN_SOURCE_MODELS_DIR, SCANDYN_INSTALL_MODELS_DIR})
    if (*d && is_file(std::string(d) + "/iiwa.urdf")) dirs.emplace_back(d);
  return dirs;
}

std::string find_model_file(const std::string& path, const std::vector<std::string>& first_dirs) {
  const bool absolute = !path.empty() && path[0] == '/';
  if (absolute) return path;
  std::vector<std::string> dirs = first_dirs;
  if (first_dirs.empty() && is_file(path)) return path;  // relative to the working directory
  for (std::string& d : model_search_dirs()) dirs.push_back(std::move(d));
  const bool has_ext = path.size() > 5 && path.compare(path.size() - 5, 5, ".urdf") == 0;
  for (const std::string& d : dirs) {
    const std::string p = d + "/" + path;
    if (is_file(p)) return p;
    if (!has_ext && is_file(p + ".urdf")) return p + ".urdf";
  }
  return first_dirs.empty() ? path : first_dirs.front() + "/" + path;
}

}  // namespace scandyn
