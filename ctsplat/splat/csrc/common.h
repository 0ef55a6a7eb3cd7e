// Shared by every kernel: thread partition, scalar exp / finiteness helpers, the row loops of one Gaussian's
// footprint and the 8-lane float vector type (GCC/Clang vector extensions: AVX2 on x86-64, SSE or NEON pairs
// elsewhere).
#pragma once

#include <math.h>
#include <unistd.h>
#include <algorithm>
#include <atomic>
#include <cmath>
#include <condition_variable>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <functional>
#include <mutex>
#include <thread>
#include <type_traits>
#include <vector>

// Persistent worker threads (no OpenMP: it would spin against torch's own pool). Starting a std::thread costs
// ~10-20 us, paid per thread and per parallel call (a fwd+bwd view makes four): at 32+ threads that alone rivals
// the work. Workers sleep on a condition variable between calls (no spinning on a shared machine). A forked child
// (new pid: the parent's workers do not exist there) builds a new pool; a call while the pool is busy (another
// Python thread: ctypes releases the GIL) starts its own threads instead of waiting.
class Pool {
  public:
    static Pool* get() {
        static std::mutex guard;
        static Pool* pool = nullptr;
        std::lock_guard<std::mutex> lk(guard);
        if (pool == nullptr || pool->pid_ != getpid()) pool = new Pool();  // never freed: workers outlive main
        return pool;
    }
    // fn(0) on the calling thread, fn(1 .. nt-1) on workers; false (nothing run) when the pool is busy
    bool try_run(int nt, const std::function<void(int)>& fn) {
        std::unique_lock<std::mutex> busy(busy_, std::try_to_lock);
        if (!busy.owns_lock()) return false;
        {
            std::lock_guard<std::mutex> lk(m_);
            while (workers_ < nt - 1) {
                const int id = ++workers_;
                const int64_t seen = gen_;
                std::thread([this, id, seen] { loop(id, seen); }).detach();
            }
            job_ = &fn; want_ = nt - 1; remaining_ = nt - 1; ++gen_;
        }
        cv_.notify_all();
        fn(0);
        std::unique_lock<std::mutex> lk(m_);
        done_.wait(lk, [&] { return remaining_ == 0; });
        job_ = nullptr;
        return true;
    }

  private:
    Pool() : pid_(getpid()) {}
    void loop(int id, int64_t seen) {
        std::unique_lock<std::mutex> lk(m_);
        for (;;) {
            cv_.wait(lk, [&] { return gen_ != seen; });
            seen = gen_;
            if (id > want_) continue;  // this call wants fewer threads
            const std::function<void(int)>* job = job_;
            lk.unlock();
            (*job)(id);
            lk.lock();
            if (--remaining_ == 0) done_.notify_one();
        }
    }
    pid_t pid_;
    std::mutex busy_, m_;
    std::condition_variable cv_, done_;
    const std::function<void(int)>* job_ = nullptr;
    int workers_ = 0, want_ = 0, remaining_ = 0;
    int64_t gen_ = 0;
};

// fn(tid) for tid in [0, nt) on nt threads (the pool's, else fresh ones)
static void run_threads(int nt, const std::function<void(int)>& fn) {
    if (nt <= 1) { fn(0); return; }
    if (Pool::get()->try_run(nt, fn)) return;
    std::vector<std::thread> threads;
    for (int k = 1; k < nt; ++k) threads.emplace_back(fn, k);
    fn(0);
    for (auto& th : threads) th.join();
}

// static block partition of [0, n) over nt threads; fn(i0, i1, tid)
template <typename F>
static void parallel_for(int64_t n, int nt, F fn) {
    if (nt < 1) nt = 1;
    if (n < 4096 || nt == 1) { fn((int64_t)0, n, 0); return; }
    run_threads(nt, [&](int k) { fn(n * k / nt, n * (k + 1) / nt, k); });
}

// tasks [0, n_tasks) claimed one at a time by nt threads (dynamic schedule: uneven work balances); fn(task, tid)
template <typename F>
static void parallel_tasks(int64_t n_tasks, int nt, F fn) {
    if (nt > n_tasks) nt = (int)n_tasks;
    if (nt <= 1) { for (int64_t k = 0; k < n_tasks; ++k) fn(k, 0); return; }
    std::atomic<int64_t> next(0);
    run_threads(nt, [&](int tid) {
        for (int64_t k = next.fetch_add(1, std::memory_order_relaxed); k < n_tasks;
             k = next.fetch_add(1, std::memory_order_relaxed))
            fn(k, tid);
    });
}

// [0, n) in chunks of `chunk` items over nt threads, dynamically scheduled (per-item work varies with the
// footprint size, so static blocks leave threads idle); fn(i0, i1) for independent per-item work
template <typename F>
static void parallel_chunks(int64_t n, int nt, int64_t chunk, F fn) {
    if (n < 4096) nt = 1;
    parallel_tasks((n + chunk - 1) / chunk, nt, [&](int64_t k, int) { fn(k * chunk, std::min(n, (k + 1) * chunk)); });
}

// Output partition for scatters: the rows (image rows, voxel planes) [0, rows) cut into bands of `size` rows and,
// per band, the items (Gaussians) whose row range meets it, in item order (CSR). A band is written by one task
// only: no per-thread copies of the output, no reduction pass, and every output element adds its items in index
// order whatever the thread count (deterministic). About 8 bands per thread balance uneven bands.
struct Bands {
    int64_t size = 1, count = 0;
    std::vector<int64_t> offsets, ids;
};

// range(i, lo, hi): item i's half-open row range (empty when lo >= hi); clipped to [0, rows) here
template <typename R>
static Bands make_bands(int64_t n, int64_t rows, int nt, R range) {
    Bands B;
    B.size = nt <= 1 ? std::max<int64_t>(rows, 1) : std::max<int64_t>(1, (rows + 8 * nt - 1) / (8 * nt));
    B.count = (rows + B.size - 1) / B.size;
    B.offsets.assign((size_t)B.count + 1, 0);
    auto bands_of = [&](int64_t i, int64_t& b0, int64_t& b1) {
        int64_t lo, hi;
        range(i, lo, hi);
        lo = std::max<int64_t>(lo, 0); hi = std::min(hi, rows);
        if (hi <= lo) { b0 = b1 = 0; return; }
        b0 = lo / B.size; b1 = (hi - 1) / B.size + 1;
    };
    for (int64_t i = 0; i < n; ++i) {
        int64_t b0, b1;
        bands_of(i, b0, b1);
        for (int64_t b = b0; b < b1; ++b) B.offsets[(size_t)b + 1] += 1;
    }
    for (int64_t b = 0; b < B.count; ++b) B.offsets[(size_t)b + 1] += B.offsets[(size_t)b];
    B.ids.resize((size_t)B.offsets[(size_t)B.count]);
    std::vector<int64_t> fill(B.offsets.begin(), B.offsets.end() - 1);
    for (int64_t i = 0; i < n; ++i) {
        int64_t b0, b1;
        bands_of(i, b0, b1);
        for (int64_t b = b0; b < b1; ++b) B.ids[(size_t)fill[(size_t)b]++] = i;
    }
    return B;
}

// C exp/expf (not std::) so that -ffast-math can vectorise the pixel loops with glibc's libmvec
static inline float ex_(float x) { return expf(x); }
static inline double ex_(double x) { return exp(x); }
// finiteness by bits (the build uses -ffast-math, under which std::isfinite may be folded to true)
static inline bool finite_(double x) { uint64_t b; std::memcpy(&b, &x, 8); return ((b >> 52) & 0x7ff) != 0x7ff; }
static inline float log1p_(float x) { return log1pf(x); }
static inline double log1p_(double x) { return log1p(x); }

// one image row of one Gaussian: row[k] += a exp(-A/2 dx^2 + by dx + cy), dx = x0 + k
template <typename T>
static inline void row_fwd(T* __restrict row, int len, T x0, T A, T by, T cy, T a) {
    const T h = (T)(-0.5) * A;
    for (int k = 0; k < len; ++k) {
        const T dx = x0 + (T)k;
        row[k] += a * ex_(h * dx * dx + by * dx + cy);
    }
}

// backward of row_fwd without the amplitude: sums of g e, g e dx, g e dx^2
template <typename T>
static inline void row_bwd(const T* __restrict g, int len, T x0, T A, T by, T cy, T* out3) {
    const T h = (T)(-0.5) * A;
    T r_e = 0, r_x = 0, r_xx = 0;
    for (int k = 0; k < len; ++k) {
        const T dx = x0 + (T)k;
        const T ge = g[k] * ex_(h * dx * dx + by * dx + cy);
        r_e += ge; r_x += ge * dx; r_xx += ge * dx * dx;
    }
    out3[0] = r_e; out3[1] = r_x; out3[2] = r_xx;
}

// 8 floats / 8 int32 masks (a true comparison is -1 in every bit)
typedef float v8f __attribute__((vector_size(32)));
typedef int32_t v8i __attribute__((vector_size(32)));
static inline v8f bc8(float s) { return (v8f){s, s, s, s, s, s, s, s}; }
static inline v8f ld8(const float* p) { v8f v; std::memcpy(&v, p, sizeof v); return v; }
static inline void st8(float* p, v8f v) { std::memcpy(p, &v, sizeof v); }
static inline v8f keep8(v8f a, v8i m) { return (v8f)((v8i)a & m); }
static inline float hsum8(v8f a) { return ((a[0] + a[1]) + (a[2] + a[3])) + ((a[4] + a[5]) + (a[6] + a[7])); }
static const v8f IOTA8 = {0.f, 1.f, 2.f, 3.f, 4.f, 5.f, 6.f, 7.f};
