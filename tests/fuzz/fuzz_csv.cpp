// tests/fuzz/fuzz_csv.cpp: libFuzzer target for the states CSV reader (the one
// `scandyn eval` uses): the bytes are a CSV file, read header and rows to the end.
// A CsvError is the expected outcome for bad input; anything else is a bug.
#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "scandyn/io/csv.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  try {
    scandyn::io::CsvReader in("fuzz.csv", std::string(reinterpret_cast<const char*>(data), size));
    std::vector<double> row;
    std::string out;
    while (in.next_row(row))
      for (double v : row) scandyn::io::append_number(out, v), out.clear();
  } catch (const scandyn::io::CsvError&) {
  }
  return 0;
}
