// scandyn/io/npy.hpp: NumPy .npy files: the header the command line writes
// (rollout's trajectories) and a reader of float32 / float64 arrays (rollout's
// torques, --tau).
//
//   io::NpyReader tau("tau.npy");              // header checked; nothing read yet
//   tau.shape();                               // e.g. {1000, 4096, 7}
//   tau.read(first, count, buffer);            // elements [first, first + count), as S
//
// The reader takes the format of numpy.save: magic "\x93NUMPY", version 1.0, 2.0 or
// 3.0, a Python-literal header dictionary {'descr': ..., 'fortran_order': ...,
// 'shape': (...)}, then the C-order data. It accepts little-endian float32 ('<f4')
// and float64 ('<f8') in C order; everything else is one InputError naming the file
// and what is wrong: not a .npy file, an unsupported version, a malformed header, a
// dtype other than those two (big-endian, integers, objects: 'descr' quoted),
// Fortran order, a shape that is not a tuple of non-negative integers, a data size
// that is not the shape's (truncated, or trailing bytes).
#pragma once

#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <string>
#include <vector>

namespace scandyn::io {

// The header of a version 1.0 .npy file holding a C-order array of `shape` with
// little-endian elements of `descr` ('<f8', '<f4'): magic, version, header length,
// the dictionary padded with spaces and a newline to a multiple of 64 bytes.
// total: pad to exactly this many bytes (a header rewritten in place), else 0.
std::string npy_header(const char* descr, const std::vector<long long>& shape, std::size_t total = 0);

// True on a little-endian machine (the only kind .npy data is read or written on).
bool little_endian();

class NpyReader {
 public:
  // Opens `path` and checks its header and its size against the shape. Throws
  // InputError (scandyn/io/limits.hpp), one line starting with the path.
  explicit NpyReader(const std::string& path);
  ~NpyReader();
  NpyReader(const NpyReader&) = delete;
  NpyReader& operator=(const NpyReader&) = delete;

  const std::string& path() const { return path_; }
  const std::vector<std::int64_t>& shape() const { return shape_; }
  std::string shape_string() const;    // "(1000, 4096, 7)", "(7,)"
  std::size_t item_size() const { return item_; }  // 4 (float32) or 8 (float64)
  const char* dtype() const { return item_ == 4 ? "float32" : "float64"; }
  std::size_t count() const { return count_; }     // elements: the product of the shape

  // Reads elements [first, first + n) (C order) into out, converted to S (float or
  // double). Throws InputError for a read that fails (the file changed since it was
  // opened) or a range beyond count().
  template <class S>
  void read(std::size_t first, std::size_t n, S* out);

 private:
  std::string path_;
  std::FILE* file_ = nullptr;
  std::vector<std::int64_t> shape_;
  std::size_t item_ = 0;
  std::size_t count_ = 0;
  std::size_t data_offset_ = 0;
  std::vector<unsigned char> scratch_;  // raw bytes of the last read
};

}  // namespace scandyn::io
