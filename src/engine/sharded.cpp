// src/engine/sharded.cpp: shard ranges, device lists, the shard pool and the merged
// status of scandyn/sharded.hpp.
#include "scandyn/sharded.hpp"

#include <algorithm>
#include <cctype>

#include "scandyn/cuda/device.hpp"

namespace scandyn {

ShardRange shard_range(Index B, int n, int k) {
  const Index base = B / n, extra = B % n;
  const Index kk = static_cast<Index>(k);
  return {kk * base + (kk < extra ? kk : extra), base + (kk < extra ? 1 : 0)};
}

Index shard_capacity(Index max_batch, int n) { return (max_batch + n - 1) / n; }

std::vector<int> parse_devices(const std::string& text) {
  if (text.empty() || text == "current") return {};
  if (text == "all") {
    const cuda::Result<int> count = cuda::device_count();
    if (!count) throw BackendError("devices 'all': " + count.error);
    if (count.value == 0) throw BackendError("devices 'all': no usable CUDA device: the CUDA runtime reports 0 devices");
    std::vector<int> all(static_cast<std::size_t>(count.value));
    for (int d = 0; d < count.value; ++d) all[static_cast<std::size_t>(d)] = d;
    return all;
  }
  std::vector<int> devices;
  std::size_t start = 0;
  while (true) {
    const std::size_t end = text.find(',', start);
    const std::string item = text.substr(start, end == std::string::npos ? std::string::npos : end - start);
    bool digits = !item.empty() && item.size() <= 6;
    for (const char c : item) digits = digits && std::isdigit(static_cast<unsigned char>(c));
    if (!digits)
      throw BackendError("devices '" + text + "': '" + item +
                         "' is not a device ordinal (expected all, current, or ordinals such as 0,1)");
    devices.push_back(std::stoi(item));
    if (end == std::string::npos) break;
    start = end + 1;
  }
  return devices;
}

std::string devices_string(const std::vector<int>& devices) {
  if (devices.empty()) return "current";
  std::string s;
  for (std::size_t k = 0; k < devices.size(); ++k) s += (k ? "," : "") + std::to_string(devices[k]);
  return s;
}

bool spans_devices(const std::vector<int>& devices) {
  if (devices.size() != 1) return devices.size() > 1;
  const cuda::Result<int> current = cuda::current_device();
  return !current || current.value != devices.front();
}

// ---- ShardPool ---------------------------------------------------------------------

ShardPool::ShardPool(std::vector<int> devices, bool cuda)
    : devices_(std::move(devices)), cuda_(cuda), errors_(devices_.size()) {
  if (devices_.empty()) throw BackendError("sharded engine: no devices");
  threads_.reserve(devices_.size());
  for (int k = 0; k < size(); ++k) threads_.emplace_back([this, k] { work(k); });
}

ShardPool::~ShardPool() {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    stop_ = true;
  }
  start_.notify_all();
  for (std::thread& t : threads_) t.join();
}

std::string ShardPool::label(int k) const {
  return cuda_ ? "device " + std::to_string(devices_[static_cast<std::size_t>(k)]) + ": "
               : "shard " + std::to_string(k) + ": ";
}

void ShardPool::work(int k) {
  std::string device_error;
  if (cuda_) {
    const cuda::Result<int> set = cuda::set_current_device(devices_[static_cast<std::size_t>(k)]);
    if (!set) device_error = set.error;
  }
  unsigned long long seen = 0;
  while (true) {
    Task* task = nullptr;
    {
      std::unique_lock<std::mutex> lock(mutex_);
      start_.wait(lock, [&] { return stop_ || generation_ != seen; });
      if (stop_) return;
      seen = generation_;
      task = task_;
    }
    std::exception_ptr error;
    try {
      if (!device_error.empty()) throw BackendError(device_error);
      (*task)(k);
    } catch (...) {
      error = std::current_exception();
    }
    {
      std::lock_guard<std::mutex> lock(mutex_);
      errors_[static_cast<std::size_t>(k)] = error;
      if (--pending_ == 0) done_.notify_all();
    }
  }
}

void ShardPool::dispatch(Task& task) {
  {
    std::unique_lock<std::mutex> lock(mutex_);
    task_ = &task;
    pending_ = size();
    ++generation_;
  }
  start_.notify_all();
  {
    std::unique_lock<std::mutex> lock(mutex_);
    done_.wait(lock, [&] { return pending_ == 0; });
    task_ = nullptr;
  }
  for (int k = 0; k < size(); ++k) {
    std::exception_ptr& e = errors_[static_cast<std::size_t>(k)];
    if (!e) continue;
    const std::exception_ptr error = e;
    for (std::exception_ptr& other : errors_) other = nullptr;
    try {
      std::rethrow_exception(error);
    } catch (const std::exception& x) {
      throw BackendError(label(k) + x.what());
    } catch (...) {
      throw BackendError(label(k) + "unknown error");
    }
  }
}

namespace detail {

void keep_failed_dofs(const BatchStatus& status, const ShardRange& r, int* failed_dof) {
  if (status.failed_dof)
    std::copy(status.failed_dof, status.failed_dof + r.count, failed_dof + r.begin);
  else
    std::fill(failed_dof + r.begin, failed_dof + r.begin + r.count, -1);
}

BatchStatus merge_shard_statuses(const std::vector<BatchStatus>& statuses, Index B, int* failed_dof) {
  const int n = static_cast<int>(statuses.size());
  BatchStatus total;
  for (int k = 0; k < n; ++k) {
    BatchStatus s = statuses[static_cast<std::size_t>(k)];
    if (s.first_instance >= 0) s.first_instance += shard_range(B, n, k).begin;
    total.merge(s);
  }
  total.failed_dof = failed_dof;
  return total;
}

}  // namespace detail
}  // namespace scandyn
