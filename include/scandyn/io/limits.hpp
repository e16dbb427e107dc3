// scandyn/io/limits.hpp: the stated limits on what scandyn reads (file sizes, nesting
// depth), the one way input files are read (regular files only, size bounded before
// reading), and the host-memory estimate that large allocations are checked against
// (docs/cli.md, "Limits").
#pragma once

#include <cstddef>
#include <cstdint>
#include <stdexcept>
#include <string>
#include <string_view>

namespace scandyn {

// An input file that cannot be read as one: missing, not a regular file (a directory,
// a FIFO, a device), larger than its stated limit, nested too deep. what() is one
// line starting with the path.
class InputError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

// Not enough memory (or disk) for what was asked. what() names what was asked, the
// bytes it needs and the bytes available.
class ResourceError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

namespace limits {

inline constexpr std::uint64_t kMaxUrdfBytes = 256ull << 20;   // 256 MiB (~500k links)
inline constexpr std::uint64_t kMaxSceneBytes = 16ull << 20;   // 16 MiB
inline constexpr std::uint64_t kMaxCsvBytes = 16ull << 30;     // 16 GiB (and the host's free memory)
inline constexpr int kMaxXmlDepth = 64;    // element nesting of a URDF (a URDF needs 4)
inline constexpr int kMaxJsonDepth = 64;   // array/object nesting of a scene (a scene needs 5)

}  // namespace limits

// Reads the whole file at path: a regular file (symbolic links followed) of at most
// max_bytes bytes; `kind` names it in messages ("URDF file", "scene file", "CSV
// file"). Opens without blocking, so a FIFO or a device is refused, never waited on.
// Throws InputError, e.g. "robot.urdf: not a regular file (a FIFO)" or "big.json:
// the file has 20000000 bytes; a scene file may have at most 16777216 (16 MiB)".
std::string read_regular_file(const std::string& path, std::uint64_t max_bytes, const char* kind);

// The deepest element nesting of XML text, counting only elements (comments,
// processing instructions, CDATA and declarations skipped); stops counting past
// limit + 1. Linear time, no recursion.
int xml_depth(std::string_view text, int limit);

// Checks JSON text before it is parsed: nesting deeper than kMaxJsonDepth and numbers
// that overflow a double are errors naming the line, column and key path
// ("dt: number 1e999 is out of range (beyond +-1.8e308)"). Strings with a NUL are
// left to the parser's caller. Throws InputError with the message (without the
// file name: the caller adds it).
void check_json_text(std::string_view text, int max_depth);

// Host memory available to a new allocation, in bytes: MemAvailable of /proc/meminfo
// (else free physical pages), capped by RLIMIT_AS / RLIMIT_DATA when set.
std::uint64_t host_memory_available();

// text with control characters and bytes >= 0x7f shown as \xNN (NUL included), so
// that a message naming a hostile path or key is one line and never cut short.
std::string printable(std::string_view text);

// "12.3 GiB" style rendering of a byte count (3 significant digits, B/KiB/MiB/GiB/TiB).
std::string format_bytes(double bytes);

// Throws ResourceError when bytes (an estimate) exceed the host's available memory:
// "<what> needs about <bytes> of host memory; <free> available".
void require_host_memory(const std::string& what, double bytes);

// Free bytes on the file system that would hold path (its directory), 0 if unknown.
double disk_space_available(const std::string& path);

// Throws ResourceError when bytes exceed the free space where path would be written
// (nothing is checked for "-" or a FIFO/device, or when the space is unknown); what
// names what is written.
void require_disk_space(const std::string& path, const std::string& what, double bytes);

// Host bytes of `threads` reference workspaces (DataTpl) for an nv-DoF model, with
// the nv x nv mass matrix when jsi is true, in scalars of `scalar` bytes.
double workspace_bytes(std::size_t nv, int threads, bool jsi, std::size_t scalar);

}  // namespace scandyn
