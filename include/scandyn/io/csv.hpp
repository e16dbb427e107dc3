// scandyn/io/csv.hpp: the numeric CSV files of `scandyn eval` (and of the later
// backends): a strict reader of a header row plus rows of finite numbers, and a
// writer that only ever shows a complete file under its final name.
//
// Dialect: fields separated by ',', no quoting; spaces and tabs around a field are
// ignored; lines end in "\n" or "\r\n"; the last line may lack its newline;
// whitespace-only lines at the end of the file are ignored (anywhere else they are
// an error). A UTF-8 byte-order mark before the header is skipped.
//
// Errors are CsvError, whose what() is one line starting with the file's path,
// e.g. "states.csv: row 7 (line 8): expected 21 fields, found 20". Rows are counted
// from 1 at the first line after the header, so row r is file line r + 1.
#pragma once

#include <cstddef>
#include <stdexcept>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "scandyn/io/output_file.hpp"

namespace scandyn::io {

// A malformed or unreadable CSV file (what(): one line naming the file).
class CsvError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

// Reads a whole CSV file of numbers: the header at construction, then one row per
// next_row(). Every field must parse as a finite number.
class CsvReader {
 public:
  // Reads the file and its header. Throws CsvError: unreadable or empty file,
  // empty column name, duplicate column name.
  explicit CsvReader(std::string path);
  // The same for CSV text already in memory (path only names it in messages).
  CsvReader(std::string path, std::string text);

  const std::string& path() const { return path_; }
  // The header's column names, trimmed, in file order.
  const std::vector<std::string>& columns() const { return columns_; }
  // 1-based number of the row last returned by next_row (0 before the first).
  std::size_t row() const { return row_; }

  // Parses the next data row into values (resized to columns().size()).
  // Returns false at the end of the data. Throws CsvError for a wrong field count,
  // an empty field, text that is not a number, NaN or Inf.
  bool next_row(std::vector<double>& values);

  // The error message prefix for data row r: "<path>: row R (line L)".
  std::string where(std::size_t r) const;
  // The same for the row last returned by next_row.
  std::string where() const { return where(row_); }

 private:
  [[noreturn]] void fail_field(std::size_t column, const std::string& what) const;
  void read_header();

  std::string path_;
  std::string text_;          // whole file contents
  std::size_t pos_ = 0;       // start of the next unread line in text_
  std::size_t data_end_ = 0;  // end of the last non-blank line
  std::size_t row_ = 0;
  std::vector<std::string> columns_;
};

// Parses a whole field (already trimmed) as a double: decimal or scientific
// notation, optional leading '+' or '-', also "nan", "inf", "infinity" (any case).
// Values below the smallest subnormal round to zero; values beyond the largest
// double become +-Inf. Returns false if text is not entirely a number.
bool parse_number(std::string_view text, double& value);

// Appends value formatted like printf("%.17g"): 17 significant digits, enough to
// read back the identical double.
void append_number(std::string& out, double value);

// "[v0, v1, ...]": n values each as append_number formats them (a JSON array of
// numbers, e.g. a scene's initial state).
std::string number_array(const double* values, std::size_t n);

// A CSV file of numbers written atomically: header, then rows.
class CsvWriter {
 public:
  explicit CsvWriter(std::string path) : file_(std::move(path)) {}

  const std::string& path() const { return file_.path(); }
  void write_header(const std::vector<std::string>& columns);
  // One row of n values, each as append_number formats it.
  void write_row(const double* values, std::size_t n);
  // Publishes the file under its final name.
  void commit() { file_.commit(); }

 private:
  AtomicFileWriter file_;
  std::string line_;
};

// Appends one line (without its newline) to the CSV file at path, creating the
// file with header_line first when it does not exist or is empty. A non-empty file
// must start with header_line (else CsvError: appending would mix formats).
void append_csv_line(const std::string& path, const std::string& header_line,
                     const std::string& line);

}  // namespace scandyn::io
