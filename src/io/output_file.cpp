// src/io/output_file.cpp: atomic output files, stdout, symbolic links, kept
// permissions, and the signal handlers that remove temporary files
// (output_file.hpp).
#include "scandyn/io/output_file.hpp"

#include <fcntl.h>
#include <limits.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <cstdlib>
#include <cstring>

#include "scandyn/io/csv.hpp"
#include "scandyn/io/limits.hpp"

namespace scandyn::io {
namespace {

// The temporary files to remove on a signal: fixed storage, so that the handler
// reads it without allocating (unlink and _exit are async-signal-safe).
constexpr int kSlots = 8;
constexpr std::size_t kPathMax = 4096;
char g_tmp[kSlots][kPathMax];
volatile std::sig_atomic_t g_used[kSlots] = {};
volatile std::sig_atomic_t g_guards = 0;    // live SignalGuards
volatile std::sig_atomic_t g_pending = 0;   // signal seen while guarded

void remove_temporaries() {
  for (int k = 0; k < kSlots; ++k)
    if (g_used[k]) ::unlink(g_tmp[k]);
}

extern "C" void on_signal(int sig) {
  if (g_guards > 0 && g_pending == 0) {
    g_pending = sig;  // the guarded command finishes by itself
    return;
  }
  remove_temporaries();
  ::_exit(128 + sig);
}

// Blocks the handled signals for the lifetime of the object (around creating a
// temporary file and recording it, so that no signal falls in between).
class BlockSignals {
 public:
  BlockSignals() {
    sigset_t set;
    sigemptyset(&set);
    for (int s : {SIGINT, SIGTERM, SIGHUP}) sigaddset(&set, s);
    ::pthread_sigmask(SIG_BLOCK, &set, &old_);
  }
  ~BlockSignals() { ::pthread_sigmask(SIG_SETMASK, &old_, nullptr); }

 private:
  sigset_t old_;
};

int register_tmp(const std::string& path) {
  if (path.size() >= kPathMax) return -1;
  for (int k = 0; k < kSlots; ++k) {
    if (g_used[k]) continue;
    std::memcpy(g_tmp[k], path.c_str(), path.size() + 1);
    g_used[k] = 1;
    return k;
  }
  return -1;
}

void unregister_tmp(int slot) {
  if (slot >= 0) g_used[slot] = 0;
}

std::string error_text() { return std::strerror(errno); }

}  // namespace

void install_signal_handlers() {
  struct sigaction sa {};
  sa.sa_handler = on_signal;
  sigemptyset(&sa.sa_mask);
  for (int s : {SIGINT, SIGTERM, SIGHUP}) sigaddset(&sa.sa_mask, s);
  sa.sa_flags = 0;
  for (int s : {SIGINT, SIGTERM, SIGHUP}) {
    struct sigaction old {};
    // a signal ignored by the parent (nohup) stays ignored
    if (::sigaction(s, nullptr, &old) == 0 && old.sa_handler == SIG_IGN) continue;
    ::sigaction(s, &sa, nullptr);
  }
}

SignalGuard::SignalGuard() { g_guards = g_guards + 1; }
SignalGuard::~SignalGuard() { g_guards = g_guards - 1; }
int SignalGuard::pending() { return static_cast<int>(g_pending); }

AtomicFileWriter::AtomicFileWriter(std::string path) : path_(std::move(path)) {
  const std::string shown = printable(path_);
  if (path_.empty()) throw CsvError("empty output path");
  if (path_.find('\0') != std::string::npos) throw CsvError(shown + ": the path contains a NUL character");
  if (path_ == "-") {
    streaming_ = true;
    fd_ = STDOUT_FILENO;
    return;
  }
  target_ = path_;
  struct stat st {};
  bool exists = false;
  if (::lstat(path_.c_str(), &st) == 0 && S_ISLNK(st.st_mode)) {
    // write the link's target, keep the link
    char* real = ::realpath(path_.c_str(), nullptr);
    if (!real)
      throw CsvError(shown + ": a symbolic link whose target cannot be resolved (" + error_text() +
                     "); not written (name the target itself)");
    target_ = real;
    std::free(real);
  }
  if (::stat(target_.c_str(), &st) == 0) {
    exists = true;
    if (S_ISDIR(st.st_mode)) throw CsvError(shown + ": is a directory");
    if (S_ISFIFO(st.st_mode) || S_ISCHR(st.st_mode)) {
      // a pipe or a device (/dev/null): written in place
      fd_ = ::open(target_.c_str(), O_WRONLY | O_CLOEXEC | O_NOCTTY);
      if (fd_ < 0) throw CsvError(shown + ": cannot open for writing: " + error_text());
      streaming_ = true;
      return;
    }
    if (!S_ISREG(st.st_mode)) throw CsvError(shown + ": not a regular file; not replaced");
  }
  const std::size_t slash = target_.rfind('/');
  const std::string dir = slash == std::string::npos ? std::string() : target_.substr(0, slash + 1);
  const std::string base = slash == std::string::npos ? target_ : target_.substr(slash + 1);
  if (base.empty()) throw CsvError(shown + ": not a file name");
  // a hidden name next to the destination, so that rename() stays on one file system
  for (unsigned attempt = 0; fd_ < 0; ++attempt) {
    tmp_path_ = dir + "." + base + ".tmp." + std::to_string(::getpid()) + "." + std::to_string(attempt);
    const BlockSignals block;
    fd_ = ::open(tmp_path_.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC, 0666);
    if (fd_ >= 0) {
      slot_ = register_tmp(tmp_path_);
      break;
    }
    if (errno != EEXIST || attempt >= 1000) {
      const std::string err = error_text();
      tmp_path_.clear();
      throw CsvError(shown + ": cannot create file: " + err);
    }
  }
  // the replaced file's permission bits (a mode-600 file stays 600)
  if (exists && ::fchmod(fd_, st.st_mode & 07777) != 0) {
    const std::string err = error_text();
    discard();
    throw CsvError(shown + ": cannot set the file mode: " + err);
  }
}

AtomicFileWriter::~AtomicFileWriter() { discard(); }

void AtomicFileWriter::discard() noexcept {
  if (streaming_) {
    if (fd_ >= 0 && fd_ != STDOUT_FILENO) ::close(fd_);
    fd_ = -1;
    return;
  }
  const BlockSignals block;
  if (fd_ >= 0) ::close(fd_);
  fd_ = -1;
  if (!tmp_path_.empty()) ::unlink(tmp_path_.c_str());
  tmp_path_.clear();
  unregister_tmp(slot_);
  slot_ = -1;
}

void AtomicFileWriter::write(std::string_view bytes) {
  buffer_.append(bytes);
  if (buffer_.size() >= (1u << 20)) flush();
}

void AtomicFileWriter::flush() {
  if (fd_ < 0) throw CsvError(printable(path_) + ": write after close");
  const char* p = buffer_.data();
  std::size_t left = buffer_.size();
  while (left > 0) {
    const ssize_t n = ::write(fd_, p, left);
    if (n < 0) {
      if (errno == EINTR) continue;
      throw CsvError(printable(path_) + ": write failed: " + error_text());
    }
    p += n;
    left -= static_cast<std::size_t>(n);
  }
  buffer_.clear();
}

void AtomicFileWriter::patch(std::uint64_t offset, std::string_view bytes) {
  if (streaming_) throw CsvError(printable(path_) + ": cannot rewrite a streamed output");
  flush();
  if (::pwrite(fd_, bytes.data(), bytes.size(), static_cast<off_t>(offset)) != static_cast<ssize_t>(bytes.size()))
    throw CsvError(printable(path_) + ": write failed: " + error_text());
}

void AtomicFileWriter::commit() {
  flush();
  if (streaming_) {
    if (fd_ != STDOUT_FILENO && ::close(fd_) != 0)
      throw CsvError(printable(path_) + ": write failed: " + error_text());
    fd_ = -1;
    return;
  }
  const int fd = fd_;
  fd_ = -1;
  if (::close(fd) != 0) throw CsvError(printable(path_) + ": write failed: " + error_text());
  if (::rename(tmp_path_.c_str(), target_.c_str()) != 0)
    throw CsvError(printable(path_) + ": cannot replace file: " + error_text());
  const BlockSignals block;
  tmp_path_.clear();
  unregister_tmp(slot_);
  slot_ = -1;
}

}  // namespace scandyn::io
