// src/io/npy.cpp: the .npy header writer and reader (scandyn/io/npy.hpp).
#include "scandyn/io/npy.hpp"

#include <sys/stat.h>

#include <cctype>
#include <cerrno>
#include <cstring>
#include <limits>
#include <string_view>

#include "scandyn/io/limits.hpp"

namespace scandyn::io {

std::string npy_header(const char* descr, const std::vector<long long>& shape, std::size_t total) {
  std::string dict = std::string("{'descr': '") + descr + "', 'fortran_order': False, 'shape': (";
  for (std::size_t k = 0; k < shape.size(); ++k)
    dict += std::to_string(shape[k]) + (shape.size() == 1 || k + 1 < shape.size() ? ", " : "");
  dict += "), }";
  const std::size_t unpadded = 10 + dict.size() + 1;
  dict.append(total > unpadded ? total - unpadded : (64 - unpadded % 64) % 64, ' ');
  dict += '\n';
  std::string h = "\x93NUMPY";
  h += '\x01';
  h += '\x00';
  const std::uint16_t len = static_cast<std::uint16_t>(dict.size());
  h += static_cast<char>(len & 0xff);
  h += static_cast<char>(len >> 8);
  return h + dict;
}

bool little_endian() {
  const std::uint16_t x = 1;
  unsigned char c;
  std::memcpy(&c, &x, 1);
  return c == 1;
}

namespace {

// A cursor over the header dictionary, a Python literal such as
//   {'descr': '<f8', 'fortran_order': False, 'shape': (3, 2, 7), }
class HeaderParser {
 public:
  HeaderParser(std::string_view text, const std::string& path) : s_(text), path_(path) {}

  [[noreturn]] void fail(const std::string& what) const {
    throw InputError(path_ + ": malformed .npy header (" + what + "): " + printable(std::string(s_.substr(0, 200))));
  }
  void skip_space() {
    while (pos_ < s_.size() && std::isspace(static_cast<unsigned char>(s_[pos_]))) ++pos_;
  }
  bool accept(char c) {
    skip_space();
    if (pos_ < s_.size() && s_[pos_] == c) return ++pos_, true;
    return false;
  }
  void expect(char c, const char* what) {
    if (!accept(c)) fail(std::string("expected '") + c + "' " + what);
  }
  std::string quoted() {
    skip_space();
    if (pos_ >= s_.size() || (s_[pos_] != '\'' && s_[pos_] != '"')) fail("expected a quoted string");
    const char q = s_[pos_++];
    const std::size_t end = s_.find(q, pos_);
    if (end == std::string_view::npos) fail("unterminated string");
    std::string r(s_.substr(pos_, end - pos_));
    pos_ = end + 1;
    return r;
  }
  std::string word() {
    skip_space();
    const std::size_t b = pos_;
    while (pos_ < s_.size() && std::isalpha(static_cast<unsigned char>(s_[pos_]))) ++pos_;
    return std::string(s_.substr(b, pos_ - b));
  }
  std::int64_t integer() {
    skip_space();
    const std::size_t b = pos_;
    std::int64_t v = 0;
    while (pos_ < s_.size() && std::isdigit(static_cast<unsigned char>(s_[pos_]))) {
      if (v > (std::numeric_limits<std::int64_t>::max() - 9) / 10) fail("a dimension is too large");
      v = v * 10 + (s_[pos_++] - '0');
    }
    if (pos_ == b) fail("a shape entry is not a non-negative integer");
    if (pos_ < s_.size() && s_[pos_] == 'L') ++pos_;  // Python 2's long suffix
    return v;
  }

 private:
  std::string_view s_;
  const std::string& path_;
  std::size_t pos_ = 0;
};

}  // namespace

NpyReader::NpyReader(const std::string& path) : path_(path) {
  struct stat st {};
  if (::stat(path.c_str(), &st) != 0) throw InputError(path + ": cannot open: " + std::strerror(errno));
  if (!S_ISREG(st.st_mode)) throw InputError(path + ": not a regular file");
  if (!little_endian()) throw InputError(path + ": .npy files are read on little-endian machines only");
  file_ = std::fopen(path.c_str(), "rb");
  if (!file_) throw InputError(path + ": cannot open: " + std::strerror(errno));
  try {
    unsigned char pre[12] = {};
    const std::size_t got = std::fread(pre, 1, 10, file_);
    if (got < 10 || std::memcmp(pre, "\x93NUMPY", 6) != 0)
      throw InputError(path + ": not a .npy file (it does not start with \\x93NUMPY; numpy.save writes them)");
    const int major = pre[6], minor = pre[7];
    std::size_t header_len = 0, prefix = 10;
    if (major == 1) {
      header_len = pre[8] | (std::size_t(pre[9]) << 8);
    } else if (major == 2 || major == 3) {
      if (std::fread(pre + 10, 1, 2, file_) != 2) throw InputError(path + ": truncated .npy header");
      header_len = pre[8] | (std::size_t(pre[9]) << 8) | (std::size_t(pre[10]) << 16) | (std::size_t(pre[11]) << 24);
      prefix = 12;
    } else {
      throw InputError(path + ": .npy format version " + std::to_string(major) + "." + std::to_string(minor) +
                       " is not supported (1.0, 2.0 and 3.0 are)");
    }
    if (header_len > (1u << 20)) throw InputError(path + ": .npy header of " + std::to_string(header_len) +
                                                   " bytes is too large (at most 1 MiB)");
    std::string header(header_len, '\0');
    if (std::fread(header.data(), 1, header_len, file_) != header_len)
      throw InputError(path + ": truncated .npy header (" + std::to_string(header_len) + " bytes announced)");
    data_offset_ = prefix + header_len;

    HeaderParser p(header, path);
    std::string descr;
    bool have_descr = false, have_order = false, have_shape = false, fortran = false;
    p.expect('{', "at the start of the dictionary");
    while (!p.accept('}')) {
      const std::string key = p.quoted();
      p.expect(':', "after a key");
      if (key == "descr") {
        descr = p.quoted();
        have_descr = true;
      } else if (key == "fortran_order") {
        const std::string w = p.word();
        if (w != "True" && w != "False") p.fail("fortran_order is neither True nor False");
        fortran = w == "True";
        have_order = true;
      } else if (key == "shape") {
        p.expect('(', "opening the shape tuple");
        while (!p.accept(')')) {
          shape_.push_back(p.integer());
          if (!p.accept(',')) {
            p.expect(')', "closing the shape tuple");
            break;
          }
        }
        have_shape = true;
      } else {
        p.fail("unknown key '" + key + "'");
      }
      if (!p.accept(',')) {
        p.expect('}', "closing the dictionary");
        break;
      }
    }
    if (!have_descr || !have_order || !have_shape) p.fail("it lacks one of 'descr', 'fortran_order', 'shape'");
    if (descr == "<f4" || (descr == "=f4")) {
      item_ = 4;
    } else if (descr == "<f8" || descr == "=f8") {
      item_ = 8;
    } else {
      throw InputError(path + ": dtype '" + printable(descr) +
                       "' is not supported: torques are little-endian float32 ('<f4') or float64 ('<f8') "
                       "(numpy.save of a float32 / float64 array)");
    }
    if (fortran && shape_.size() > 1)
      throw InputError(path + ": the array is in Fortran order: save a C-order array "
                       "(numpy.save(path, numpy.ascontiguousarray(a)))");
    count_ = 1;
    for (std::int64_t d : shape_) {
      if (d != 0 && count_ > std::numeric_limits<std::size_t>::max() / 16 / static_cast<std::size_t>(d))
        throw InputError(path + ": shape " + shape_string() + " is too large");
      count_ *= static_cast<std::size_t>(d);
    }
    const std::size_t want = data_offset_ + count_ * item_;
    const std::size_t have = static_cast<std::size_t>(st.st_size);
    if (have < want)
      throw InputError(path + ": truncated: a " + dtype() + " array of shape " + shape_string() + " needs " +
                       std::to_string(want - data_offset_) + " bytes of data, the file holds " +
                       std::to_string(have > data_offset_ ? have - data_offset_ : 0));
    if (have > want)
      throw InputError(path + ": " + std::to_string(have - want) + " bytes after the data of the " + dtype() +
                       " array of shape " + shape_string() + " (not one .npy array)");
  } catch (...) {
    std::fclose(file_);
    file_ = nullptr;
    throw;
  }
}

NpyReader::~NpyReader() {
  if (file_) std::fclose(file_);
}

std::string NpyReader::shape_string() const {
  std::string s = "(";
  for (std::size_t k = 0; k < shape_.size(); ++k) s += (k ? ", " : "") + std::to_string(shape_[k]);
  return s + (shape_.size() == 1 ? ",)" : ")");
}

template <class S>
void NpyReader::read(std::size_t first, std::size_t n, S* out) {
  if (first > count_ || n > count_ - first)
    throw InputError(path_ + ": read of elements [" + std::to_string(first) + ", " + std::to_string(first + n) +
                     ") beyond the array's " + std::to_string(count_));
  if (n == 0) return;
  const long offset = static_cast<long>(data_offset_ + first * item_);
  const bool direct = item_ == sizeof(S);
  unsigned char* dst = reinterpret_cast<unsigned char*>(out);
  if (!direct) {
    scratch_.resize(n * item_);
    dst = scratch_.data();
  }
  if (std::fseek(file_, offset, SEEK_SET) != 0 || std::fread(dst, item_, n, file_) != n)
    throw InputError(path_ + ": cannot read elements [" + std::to_string(first) + ", " + std::to_string(first + n) +
                     ") (the file changed or was truncated since it was opened)");
  if (direct) return;
  if (item_ == 4) {
    for (std::size_t k = 0; k < n; ++k) {
      float v;
      std::memcpy(&v, dst + 4 * k, 4);
      out[k] = static_cast<S>(v);
    }
  } else {
    for (std::size_t k = 0; k < n; ++k) {
      double v;
      std::memcpy(&v, dst + 8 * k, 8);
      out[k] = static_cast<S>(v);
    }
  }
}

template void NpyReader::read<float>(std::size_t, std::size_t, float*);
template void NpyReader::read<double>(std::size_t, std::size_t, double*);

}  // namespace scandyn::io
