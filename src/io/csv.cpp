// src/io/csv.cpp: strict numeric CSV reading and atomic CSV writing.
#include "scandyn/io/csv.hpp"

#include "scandyn/io/limits.hpp"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <charconv>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <unordered_map>

namespace scandyn::io {
namespace {

bool is_blank(char c) { return c == ' ' || c == '\t'; }

std::string_view trim(std::string_view s) {
  while (!s.empty() && is_blank(s.front())) s.remove_prefix(1);
  while (!s.empty() && (is_blank(s.back()) || s.back() == '\r')) s.remove_suffix(1);
  return s;
}

std::string system_error_text() { return std::strerror(errno); }

// The whole file (a regular file within the stated limit), or CsvError.
std::string read_file(const std::string& path) {
  try {
    return read_regular_file(path, limits::kMaxCsvBytes, "CSV file");
  } catch (const InputError& e) {
    throw CsvError(e.what());
  }
}

}  // namespace

// ---- parsing and formatting numbers -------------------------------------------

bool parse_number(std::string_view text, double& value) {
  if (!text.empty() && text.front() == '+') {
    text.remove_prefix(1);
    if (!text.empty() && (text.front() == '+' || text.front() == '-')) return false;
  }
  if (text.empty()) return false;
  const char* first = text.data();
  const char* last = first + text.size();
  double v = 0;
  const auto [ptr, ec] = std::from_chars(first, last, v, std::chars_format::general);
  if (ptr != last) return false;
  if (ec == std::errc::result_out_of_range) {
    // from_chars reports both overflow and underflow; strtod tells them apart
    const std::string copy(text);
    v = std::strtod(copy.c_str(), nullptr);
  } else if (ec != std::errc()) {
    return false;
  }
  value = v;
  return true;
}

void append_number(std::string& out, double value) {
  char buf[40];
  const auto res = std::to_chars(buf, buf + sizeof buf, value, std::chars_format::general, 17);
  out.append(buf, res.ptr);
}

std::string number_array(const double* values, std::size_t n) {
  std::string a = "[";
  for (std::size_t i = 0; i < n; ++i) {
    if (i) a += ", ";
    append_number(a, values[i]);
  }
  return a + "]";
}

// ---- reader -------------------------------------------------------------------

CsvReader::CsvReader(std::string path) : path_(std::move(path)), text_(read_file(path_)) { read_header(); }

CsvReader::CsvReader(std::string path, std::string text) : path_(std::move(path)), text_(std::move(text)) {
  read_header();
}

void CsvReader::read_header() {
  path_ = printable(path_);
  // a CR that does not end a CRLF pair: a file with CR-only line ends (classic Mac)
  // would otherwise read as one long header line
  for (std::size_t k = text_.find('\r'); k != std::string::npos; k = text_.find('\r', k + 1)) {
    if (k + 1 < text_.size() && text_[k + 1] != '\n') {
      const std::size_t line = 1 + static_cast<std::size_t>(std::count(text_.begin(), text_.begin() + k, '\n'));
      throw CsvError(path_ + ": line " + std::to_string(line) +
                     ": a carriage return (CR) not followed by LF; lines must end in LF or CRLF "
                     "(CR-only line ends are not read)");
    }
  }
  // skip a UTF-8 byte-order mark
  if (text_.compare(0, 3, "\xEF\xBB\xBF") == 0) pos_ = 3;
  // trailing whitespace-only lines are not data
  data_end_ = text_.size();
  while (data_end_ > pos_ && std::strchr(" \t\r\n", text_[data_end_ - 1]) != nullptr) --data_end_;
  if (data_end_ <= pos_) throw CsvError(path_ + ": empty file (expected a header row)");

  std::size_t eol = text_.find('\n', pos_);
  if (eol == std::string::npos) eol = text_.size();
  const std::string_view header = trim(std::string_view(text_).substr(pos_, eol - pos_));
  pos_ = eol + 1;
  if (header.empty()) throw CsvError(path_ + ": line 1 is empty (expected the header row)");

  std::unordered_map<std::string_view, std::size_t> seen;
  std::size_t start = 0;
  for (;;) {
    const std::size_t comma = header.find(',', start);
    const std::string_view name = trim(header.substr(
        start, comma == std::string_view::npos ? std::string_view::npos : comma - start));
    const std::size_t col = columns_.size() + 1;
    if (name.empty())
      throw CsvError(path_ + ": header: column " + std::to_string(col) + " has an empty name");
    const auto [it, inserted] = seen.emplace(name, col);
    if (!inserted)
      throw CsvError(path_ + ": duplicate column " + printable(name.substr(0, 100)) + " (columns " +
                     std::to_string(it->second) + " and " + std::to_string(col) + ")");
    columns_.emplace_back(name);
    if (comma == std::string_view::npos) break;
    start = comma + 1;
  }
}

std::string CsvReader::where(std::size_t r) const {
  return path_ + ": row " + std::to_string(r) + " (line " + std::to_string(r + 1) + ")";
}

void CsvReader::fail_field(std::size_t column, const std::string& what) const {
  throw CsvError(where() + ", column " + printable(columns_[column].substr(0, 100)) + ": " + what);
}

bool CsvReader::next_row(std::vector<double>& values) {
  if (pos_ >= data_end_) return false;
  ++row_;
  std::size_t eol = text_.find('\n', pos_);
  if (eol == std::string::npos) eol = text_.size();
  const std::string_view line = std::string_view(text_).substr(pos_, eol - pos_);
  pos_ = eol + 1;
  if (trim(line).empty()) throw CsvError(where() + ": empty line");

  const std::size_t ncol = columns_.size();
  values.resize(ncol);
  std::size_t field = 0, start = 0;
  for (;;) {
    const std::size_t comma = line.find(',', start);
    if (field < ncol) {
      const std::string_view text = trim(line.substr(
          start, comma == std::string_view::npos ? std::string_view::npos : comma - start));
      double v = 0;
      if (text.empty()) fail_field(field, "empty field");
      if (!parse_number(text, v))
        fail_field(field, "not a number: '" + printable(text.substr(0, 60)) + (text.size() > 60 ? "...'" : "'"));
      if (std::isnan(v)) fail_field(field, "NaN");
      if (std::isinf(v)) fail_field(field, v > 0 ? "Inf" : "-Inf");
      values[field] = v;
    }
    ++field;
    if (comma == std::string_view::npos) break;
    start = comma + 1;
  }
  if (field != ncol)
    throw CsvError(where() + ": expected " + std::to_string(ncol) + " fields, found " +
                   std::to_string(field));
  return true;
}

// ---- CSV writer ---------------------------------------------------------------

void CsvWriter::write_header(const std::vector<std::string>& columns) {
  line_.clear();
  for (std::size_t c = 0; c < columns.size(); ++c) {
    if (c) line_ += ',';
    line_ += columns[c];
  }
  line_ += '\n';
  file_.write(line_);
}

void CsvWriter::write_row(const double* values, std::size_t n) {
  line_.clear();
  for (std::size_t c = 0; c < n; ++c) {
    if (c) line_ += ',';
    append_number(line_, values[c]);
  }
  line_ += '\n';
  file_.write(line_);
}

// ---- appending ----------------------------------------------------------------

void append_csv_line(const std::string& path, const std::string& header_line,
                     const std::string& line) {
  const int fd = ::open(path.c_str(), O_RDWR | O_CREAT | O_APPEND | O_CLOEXEC, 0666);
  if (fd < 0) throw CsvError(path + ": cannot open for appending: " + system_error_text());
  std::string bytes;
  std::string error;
  struct stat st {};
  if (::fstat(fd, &st) != 0) error = path + ": cannot stat: " + system_error_text();
  if (error.empty() && st.st_size == 0) {
    bytes = header_line + "\n";
  } else if (error.empty()) {
    // the existing header must be ours; a missing final newline is supplied
    std::string head(
        std::min<std::size_t>(static_cast<std::size_t>(st.st_size), header_line.size() + 2), '\0');
    char last = '\n';
    if (::pread(fd, &head[0], head.size(), 0) != static_cast<ssize_t>(head.size()) ||
        ::pread(fd, &last, 1, st.st_size - 1) != 1) {
      error = path + ": cannot read: " + system_error_text();
    } else {
      const std::size_t eol = head.find('\n');
      const std::string first(trim(std::string_view(head).substr(0, eol)));
      if (first != header_line)
        error = path + ": existing header does not match (expected " + header_line + ")";
      else if (last != '\n')
        bytes = "\n";
    }
  }
  if (error.empty()) {
    bytes += line + "\n";
    const ssize_t n =
        ::write(fd, bytes.data(), bytes.size());  // one write: O_APPEND keeps it whole
    if (n != static_cast<ssize_t>(bytes.size()))
      error = path + ": write failed: " + system_error_text();
  }
  if (::close(fd) != 0 && error.empty()) error = path + ": write failed: " + system_error_text();
  if (!error.empty()) throw CsvError(error);
}

}  // namespace scandyn::io
