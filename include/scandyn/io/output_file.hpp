// scandyn/io/output_file.hpp: how scandyn writes the files other programs read
// (docs/cli.md, "Output files"):
//  - through a hidden temporary file in the destination's directory, renamed onto
//    the destination only when complete (an error leaves nothing, an existing file
//    untouched);
//  - "-" writes to stdout, and an existing FIFO or character device (/dev/null) is
//    written in place, streamed (no temporary file: such an output cannot be taken
//    back, and the exit status tells whether it is complete);
//  - a symbolic link is followed: its target is replaced (a dangling link is
//    refused), and an existing destination keeps its permission bits;
//  - SIGINT, SIGTERM and SIGHUP remove every temporary file and exit with 128 +
//    the signal number; a command that asked to finish cooperatively
//    (SignalGuard) is told instead, at its next check, and may publish what it has
//    (rollout: the records written so far).
#pragma once

#include <csignal>
#include <cstdint>
#include <string>
#include <string_view>

namespace scandyn::io {

// Installs the SIGINT / SIGTERM / SIGHUP handlers (main() calls it once).
void install_signal_handlers();

// While one exists, a first signal does not end the process: it is recorded for
// pending() to report, and the command finishes by itself (a second signal ends it
// as usual).
class SignalGuard {
 public:
  SignalGuard();
  ~SignalGuard();
  SignalGuard(const SignalGuard&) = delete;
  SignalGuard& operator=(const SignalGuard&) = delete;
  // The signal received since the guard was made, 0 if none.
  static int pending();
};

// Writes a file through a temporary file in the destination directory, renamed
// onto path by commit(). Without commit() (an error, an exception, a signal) the
// temporary file is removed and an existing file at path is left untouched.
class AtomicFileWriter {
 public:
  // Creates the temporary file (or opens stdout / the FIFO or device). Throws
  // CsvError (e.g. missing directory, a dangling symbolic link, a directory).
  explicit AtomicFileWriter(std::string path);
  ~AtomicFileWriter();
  AtomicFileWriter(const AtomicFileWriter&) = delete;
  AtomicFileWriter& operator=(const AtomicFileWriter&) = delete;

  // The destination as given ("-" for stdout).
  const std::string& path() const { return path_; }
  // True when writing to stdout, a FIFO or a device: no temporary file, nothing to
  // patch, commit() only flushes.
  bool streaming() const { return streaming_; }
  // Buffered write. Throws CsvError on a write error (e.g. disk full).
  void write(std::string_view bytes);
  // Writes the buffered bytes to the file.
  void flush();
  // Overwrites bytes at offset of what was written (after flushing; not when
  // streaming). Throws CsvError.
  void patch(std::uint64_t offset, std::string_view bytes);
  // Flushes, closes and renames the temporary file onto the destination. Throws CsvError.
  void commit();

 private:
  void discard() noexcept;

  std::string path_;         // as given
  std::string target_;       // the file replaced (a symbolic link's target)
  std::string tmp_path_;
  int fd_ = -1;
  int slot_ = -1;            // in the signal handler's list of temporary files
  bool streaming_ = false;
  std::string buffer_;
};

}  // namespace scandyn::io
