// Parallel loops of the native library on helper threads that the caller never waits for.
//
// A loop is split into chunks, and its caller works through them itself. Helper threads, started
// on first use and asleep between loops (blocked on a condition variable, never spinning), join in
// when the scheduler runs them, each claiming chunks until none is left. The caller then waits
// only for the chunks a helper has already claimed, never for a helper to wake up. On a busy
// machine a helper that gets no time slice costs the loop nothing, and the loop runs as on one
// thread; on an idle one the helpers share the work.
//
// A thread started per loop and joined at its end (this library before December 2026) has to be
// scheduled in every loop. Under a background load that wait cost more than the thread saved:
// point-to-plane ICP on the 130k-point Kinect 1 cm pair took 1.4-2.2x its idle time with two
// threads per loop, and 1.3-1.5x with one (issue 31).
//
// Loops may run at once (two XLA threads in custom calls, a loop inside a chunk of another):
// helpers take chunks from any open loop with a free seat.
#ifndef LIEAX_PARALLEL_H_
#define LIEAX_PARALLEL_H_

#include <algorithm>
#include <atomic>
#include <condition_variable>
#include <cstdint>
#include <mutex>
#include <thread>
#include <vector>

namespace lieax {

class Helpers {
 public:
  // f(chunk) for every chunk in [0, chunks), on the caller and at most `threads - 1` helpers.
  template <typename F>
  static void For(int64_t chunks, int threads, const F& f) {
    if (threads <= 1 || chunks <= 1) {
      for (int64_t c = 0; c < chunks; ++c) f(c);
      return;
    }
    auto call = [](const void* fn, int64_t c) { (*static_cast<const F*>(fn))(c); };
    Loop loop(call, &f, chunks, static_cast<int>(std::min<int64_t>(threads, chunks)) - 1);
    Instance().Run(loop);
  }

 private:
  struct Loop {
    Loop(void (*call)(const void*, int64_t), const void* fn, int64_t chunks, int seats)
        : call(call), fn(fn), chunks(chunks), seats(seats) {}
    bool Claim(int64_t& c) {
      c = next.fetch_add(1, std::memory_order_relaxed);
      return c < chunks;
    }
    void Drain(int64_t c) {
      do call(fn, c);
      while (Claim(c));
    }
    void (*call)(const void*, int64_t);
    const void* fn;
    const int64_t chunks;
    std::atomic<int64_t> next{0};
    int seats;       // helpers that may still join (guarded by the mutex)
    int active = 0;  // helpers inside Drain (guarded by the mutex)
  };

  static Helpers& Instance() {
    static Helpers* helpers = new Helpers;  // never destroyed: its threads sleep until exit
    return *helpers;
  }

  void Run(Loop& loop) {
    {
      std::lock_guard<std::mutex> lock(mutex_);
      const uint64_t seen = generation_;
      while (started_ < loop.seats) {
        std::thread([this, seen] { Serve(seen); }).detach();
        ++started_;
      }
      open_.push_back(&loop);
      ++generation_;
    }
    wake_.notify_all();
    int64_t c;
    if (loop.Claim(c)) loop.Drain(c);
    // Every chunk is claimed: close the loop to helpers not yet in it, and wait for those in it.
    std::unique_lock<std::mutex> lock(mutex_);
    open_.erase(std::find(open_.begin(), open_.end(), &loop));
    done_.wait(lock, [&] { return loop.active == 0; });
  }

  // A helper: wakes on every new loop and claims a first chunk under the mutex, so that a loop
  // closed after that claim waits for it and one closed before it never sees this helper.
  void Serve(uint64_t seen) {
    std::unique_lock<std::mutex> lock(mutex_);
    for (;;) {
      wake_.wait(lock, [&] { return generation_ != seen; });
      seen = generation_;
      for (Loop* loop = Pick(); loop != nullptr; loop = Pick()) {
        int64_t c;
        if (!loop->Claim(c)) continue;  // (Pick skips it from now on: no seat is left)
        ++loop->active;
        lock.unlock();
        loop->Drain(c);
        lock.lock();
        if (--loop->active == 0) done_.notify_all();
      }
    }
  }

  // An open loop with a free seat, its seat taken (under the mutex); null when there is none.
  Loop* Pick() {
    for (Loop* loop : open_) {
      if (loop->seats > 0 && loop->next.load(std::memory_order_relaxed) < loop->chunks) {
        --loop->seats;
        return loop;
      }
    }
    return nullptr;
  }

  std::mutex mutex_;
  std::condition_variable wake_, done_;
  std::vector<Loop*> open_;
  uint64_t generation_ = 0;
  int started_ = 0;
};

}  // namespace lieax

#endif  // LIEAX_PARALLEL_H_
