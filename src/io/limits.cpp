// src/io/limits.cpp: reading input files within the stated limits, the
// pre-parse checks of XML and JSON text, and the host-memory and disk estimates
// (scandyn/io/limits.hpp, docs/cli.md "Limits").
#include "scandyn/io/limits.hpp"

#include <fcntl.h>
#include <sys/resource.h>
#include <sys/stat.h>
#include <sys/statvfs.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <vector>

namespace scandyn {

std::string printable(std::string_view text) {
  std::string out;
  out.reserve(text.size());
  for (const char ch : text) {
    const auto c = static_cast<unsigned char>(ch);
    if (c < 0x20 || c == 0x7f) {
      char buf[8];
      std::snprintf(buf, sizeof buf, "\\x%02x", c);
      out += buf;
    } else {
      out += ch;
    }
  }
  return out;
}

namespace {

const char* file_type(mode_t m) {
  if (S_ISDIR(m)) return "a directory";
  if (S_ISFIFO(m)) return "a FIFO";
  if (S_ISCHR(m)) return "a character device";
  if (S_ISBLK(m)) return "a block device";
  if (S_ISSOCK(m)) return "a socket";
  return "not a plain file";
}

}  // namespace

std::string format_bytes(double bytes) {
  static const char* const units[] = {"B", "KiB", "MiB", "GiB", "TiB", "PiB", "EiB"};
  int u = 0;
  while (bytes >= 1024 && u < 6) bytes /= 1024, ++u;
  char buf[48];
  if (u == 0) std::snprintf(buf, sizeof buf, "%.0f B", bytes);
  else std::snprintf(buf, sizeof buf, "%.3g %s", bytes, units[u]);
  return buf;
}

std::string read_regular_file(const std::string& path, std::uint64_t max_bytes, const char* kind) {
  const std::string shown = printable(path);
  if (path.empty()) throw InputError(std::string("empty path given for a ") + kind);
  if (path.find('\0') != std::string::npos)
    throw InputError(shown + ": the path contains a NUL character");
  // O_NONBLOCK: opening a FIFO for reading must not wait for a writer
  const int fd = ::open(path.c_str(), O_RDONLY | O_NONBLOCK | O_CLOEXEC | O_NOCTTY);
  if (fd < 0) throw InputError(shown + ": cannot open file: " + std::strerror(errno));
  struct stat st {};
  if (::fstat(fd, &st) != 0) {
    const std::string err = std::strerror(errno);
    ::close(fd);
    throw InputError(shown + ": cannot stat: " + err);
  }
  if (!S_ISREG(st.st_mode)) {
    ::close(fd);
    throw InputError(shown + ": not a regular file (" + file_type(st.st_mode) + "); a " + kind +
                     " must be a regular file");
  }
  const auto too_big = [&](std::uint64_t size) {
    ::close(fd);
    throw InputError(shown + ": the file has " + std::to_string(size) + " bytes; a " + kind +
                     " may have at most " + std::to_string(max_bytes) + " (" +
                     format_bytes(static_cast<double>(max_bytes)) + ")");
  };
  const std::uint64_t size = st.st_size > 0 ? static_cast<std::uint64_t>(st.st_size) : 0;
  if (size > max_bytes) too_big(size);
  if (const std::uint64_t avail = host_memory_available(); avail && size > avail) {
    ::close(fd);
    throw ResourceError(shown + ": reading the " + kind + " (" + format_bytes(double(size)) + ") needs that much host memory; " +
                        format_bytes(double(avail)) + " available");
  }
  const int flags = ::fcntl(fd, F_GETFL);
  if (flags >= 0) ::fcntl(fd, F_SETFL, flags & ~O_NONBLOCK);
  std::string text;
  try {
    text.reserve(static_cast<std::size_t>(size));
  } catch (const std::bad_alloc&) {
    ::close(fd);
    throw ResourceError(shown + ": reading the " + kind + " needs " + format_bytes(double(size)) +
                        " of host memory; " + format_bytes(double(host_memory_available())) + " available");
  }
  std::vector<char> buf(1 << 16);
  for (;;) {
    const ssize_t n = ::read(fd, buf.data(), buf.size());
    if (n == 0) break;
    if (n < 0) {
      if (errno == EINTR) continue;
      const std::string err = std::strerror(errno);
      ::close(fd);
      throw InputError(shown + ": cannot read: " + err);
    }
    if (text.size() + static_cast<std::size_t>(n) > max_bytes) too_big(text.size() + static_cast<std::size_t>(n));
    text.append(buf.data(), static_cast<std::size_t>(n));
  }
  ::close(fd);
  return text;
}

int xml_depth(std::string_view t, int limit) {
  const std::size_t n = t.size();
  int depth = 0, deepest = 0;
  auto skip_past = [&](std::size_t from, std::string_view end) {
    const std::size_t k = t.find(end, from);
    return k == std::string_view::npos ? n : k + end.size();
  };
  std::size_t i = 0;
  while (i < n) {
    const std::size_t lt = t.find('<', i);
    if (lt == std::string_view::npos) break;
    const std::string_view rest = t.substr(lt);
    if (rest.compare(0, 4, "<!--") == 0) {
      i = skip_past(lt + 4, "-->");
    } else if (rest.compare(0, 9, "<![CDATA[") == 0) {
      i = skip_past(lt + 9, "]]>");
    } else if (rest.compare(0, 2, "<?") == 0) {
      i = skip_past(lt + 2, "?>");
    } else if (rest.compare(0, 2, "<!") == 0) {
      // a declaration (DOCTYPE with an internal subset in brackets)
      int brackets = 0;
      std::size_t k = lt + 2;
      for (; k < n; ++k) {
        if (t[k] == '[') ++brackets;
        else if (t[k] == ']') --brackets;
        else if (t[k] == '>' && brackets <= 0) break;
      }
      i = k + 1;
    } else if (rest.compare(0, 2, "</") == 0) {
      if (depth > 0) --depth;
      i = skip_past(lt + 2, ">");
    } else {
      // a start tag: up to its '>' outside quoted attribute values
      std::size_t k = lt + 1;
      char quote = 0;
      for (; k < n; ++k) {
        const char c = t[k];
        if (quote) {
          if (c == quote) quote = 0;
        } else if (c == '"' || c == '\'') {
          quote = c;
        } else if (c == '>') {
          break;
        }
      }
      const bool self_closing = k < n && k > lt + 1 && t[k - 1] == '/';
      deepest = std::max(deepest, depth + 1);
      if (!self_closing) ++depth;
      if (deepest > limit) return deepest;
      i = k + 1;
    }
  }
  return deepest;
}

namespace {

// The position of byte offset k as "line L, column C" (1-based).
std::string line_column(std::string_view t, std::size_t k) {
  std::size_t line = 1, col = 1;
  for (std::size_t i = 0; i < k && i < t.size(); ++i) {
    if (t[i] == '\n') ++line, col = 1;
    else ++col;
  }
  return "line " + std::to_string(line) + ", column " + std::to_string(col);
}

struct JsonFrame {
  bool object;
  bool want_key;      // object: the next string is a member name
  std::string key;    // object: the current member name
  std::size_t index;  // array: the current element
};

std::string json_path(const std::vector<JsonFrame>& frames) {
  std::string p;
  for (const JsonFrame& f : frames) {
    if (f.object) {
      if (f.want_key) break;  // between members
      std::string k = printable(f.key);
      if (k.size() > 40) k = k.substr(0, 37) + "...";
      p += (p.empty() ? "" : ".") + k;
    } else {
      p += "[" + std::to_string(f.index) + "]";
    }
    if (p.size() > 60) return p + "...";
  }
  return p;
}

}  // namespace

void check_json_text(std::string_view t, int max_depth) {
  std::vector<JsonFrame> frames;
  const std::size_t n = t.size();
  auto fail = [&](std::size_t at, const std::string& what) {
    const std::string path = json_path(frames);
    throw InputError((path.empty() ? "" : path + ": ") + line_column(t, at) + ": " + what);
  };
  for (std::size_t i = 0; i < n;) {
    const char c = t[i];
    if (c == '"') {
      std::size_t k = i + 1;
      while (k < n && t[k] != '"') k += t[k] == '\\' ? 2 : 1;
      if (!frames.empty() && frames.back().object && frames.back().want_key)
        frames.back().key = std::string(t.substr(i + 1, std::min(k, n) - i - 1));
      i = k + 1;
    } else if (c == '{' || c == '[') {
      if (static_cast<int>(frames.size()) >= max_depth)
        fail(i, "nested deeper than " + std::to_string(max_depth) + " levels of arrays and objects");
      frames.push_back({c == '{', c == '{', "", 0});
      ++i;
    } else if (c == '}' || c == ']') {
      if (!frames.empty()) frames.pop_back();
      ++i;
    } else if (c == ':') {
      if (!frames.empty() && frames.back().object) frames.back().want_key = false;
      ++i;
    } else if (c == ',') {
      if (!frames.empty()) {
        if (frames.back().object) frames.back().want_key = true;
        else ++frames.back().index;
      }
      ++i;
    } else if (c == '-' || (c >= '0' && c <= '9')) {
      std::size_t k = i;
      while (k < n && (std::strchr("+-.eE", t[k]) != nullptr || (t[k] >= '0' && t[k] <= '9'))) ++k;
      const std::string number(t.substr(i, k - i));
      errno = 0;
      const double v = std::strtod(number.c_str(), nullptr);
      if (errno == ERANGE && std::isinf(v)) {
        std::string shown = number.size() > 40 ? number.substr(0, 37) + "..." : number;
        fail(i, "number " + shown + " is out of range (a double holds at most +-1.8e308)");
      }
      i = k;
    } else {
      ++i;
    }
  }
}

std::uint64_t host_memory_available() {
  std::uint64_t avail = 0;
  {
    std::ifstream f("/proc/meminfo");
    std::string key;
    std::uint64_t kb = 0;
    std::string unit;
    while (f >> key >> kb) {
      std::getline(f, unit);
      if (key == "MemAvailable:") {
        avail = kb * 1024;
        break;
      }
    }
  }
  if (avail == 0) {
    const long pages = ::sysconf(_SC_AVPHYS_PAGES), page = ::sysconf(_SC_PAGESIZE);
    if (pages > 0 && page > 0) avail = static_cast<std::uint64_t>(pages) * static_cast<std::uint64_t>(page);
  }
  // a cgroup (v2) memory limit
  {
    std::ifstream mx("/sys/fs/cgroup/memory.max"), cur("/sys/fs/cgroup/memory.current");
    std::string m;
    std::uint64_t used = 0;
    if (mx >> m && m != "max" && cur >> used) {
      const std::uint64_t limit = std::strtoull(m.c_str(), nullptr, 10);
      if (limit > used) avail = avail ? std::min(avail, limit - used) : limit - used;
    }
  }
  for (const int res : {RLIMIT_AS, RLIMIT_DATA}) {
    struct rlimit rl {};
    if (::getrlimit(res, &rl) == 0 && rl.rlim_cur != RLIM_INFINITY)
      avail = avail ? std::min<std::uint64_t>(avail, rl.rlim_cur) : rl.rlim_cur;
  }
  return avail;
}

void require_host_memory(const std::string& what, double bytes) {
  const std::uint64_t avail = host_memory_available();
  if (avail == 0) return;  // unknown: let the allocation decide
  if (!(bytes <= static_cast<double>(avail)))
    throw ResourceError(what + " needs about " + format_bytes(bytes) + " of host memory; " +
                        format_bytes(static_cast<double>(avail)) + " available");
}

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

}  // namespace scandyn
