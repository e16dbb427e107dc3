// src/cli/resources.cpp: memory and disk estimates (resources.hpp).
#include "resources.hpp"

#include <sys/stat.h>
#include <sys/statvfs.h>

#include "scandyn/limits.hpp"

namespace scandyn::cli {

double disk_space_available(const std::string& path) {
  const std::size_t slash = path.rfind('/');
  const std::string dir = slash == std::string::npos ? "." : slash == 0 ? "/" : path.substr(0, slash);
  struct statvfs vfs {};
  if (::statvfs(dir.c_str(), &vfs) != 0) return 0;
  return static_cast<double>(vfs.f_bavail) * static_cast<double>(vfs.f_frsize);
}

void require_disk_space(const std::string& path, const std::string& what, double bytes) {
  if (path == "-") return;
  struct stat st {};
  if (::stat(path.c_str(), &st) == 0 && (S_ISFIFO(st.st_mode) || S_ISCHR(st.st_mode))) return;
  const double free_bytes = disk_space_available(path);
  if (free_bytes <= 0) return;
  if (bytes > free_bytes)
    throw ResourceError(what + " needs about " + format_bytes(bytes) + " of disk space for " + printable(path) +
                        "; " + format_bytes(free_bytes) + " free there");
}

double workspace_bytes(std::size_t nv, int threads, bool jsi, std::size_t scalar) {
  // DataTpl: ~90 scalars per body (transforms, motions, forces, inertias, ABA terms)
  const double n = static_cast<double>(nv), s = static_cast<double>(scalar);
  double per_thread = n * 90 * s;
  if (jsi) per_thread += n * n * s;
  return per_thread * static_cast<double>(threads < 1 ? 1 : threads);
}

int planned_threads(BackendKind backend, int threads_flag) {
  if (backend != BackendKind::OpenMP) return 1;
  return threads_flag > 0 ? threads_flag : openmp_threads();
}

}  // namespace scandyn::cli
