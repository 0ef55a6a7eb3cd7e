// Shared by every kernel: the worker pool and thread partitions, scalar exp / finiteness helpers, the row loops of
// one Gaussian's footprint and the 8-lane float vector type (GCC/Clang vector extensions: AVX2 on x86-64, SSE or
// NEON pairs elsewhere).
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
#include <mutex>
#include <thread>
#include <type_traits>
#include <vector>

// Subnormal numbers flushed to zero while a kernel runs, as the kernels were built and timed (denormal arithmetic
// is up to ~100x slower on x86 and exp() of a far pixel's offset lands there), and restored afterwards: the
// process's own mode stays as it was (a library built with -ffast-math would set it for the whole process).
#if defined(__SSE2__) || defined(__x86_64__)
#include <xmmintrin.h>
struct FlushDenormals {
    unsigned int saved;
    FlushDenormals() : saved(_mm_getcsr()) { _mm_setcsr(saved | 0x8040u); }  // FTZ (bit 15) | DAZ (bit 6)
    ~FlushDenormals() { _mm_setcsr(saved); }
    FlushDenormals(const FlushDenormals&) = delete;
    FlushDenormals& operator=(const FlushDenormals&) = delete;
};
#else
struct FlushDenormals {};
#endif

// Worker threads kept between kernel calls: starting a std::thread costs tens of microseconds, which at one call per
// kernel and 16-128 cores would cost more than a small kernel's work. Workers sleep on a condition variable between
// parallel regions (no spinning against torch's own threads). One region at a time per process: a second caller (a
// ctypes call releases the GIL, so two Python threads can be here at once) starts threads of its own instead. A
// forked child (the workers are not copied into it) gets a new pool; the parent's is left untouched.
class WorkerPool {
  public:
    // fn(k) for k = 0 .. nt - 1, k = 0 on the calling thread; false (nothing run) while another region runs
    template <typename F>
    bool run(int nt, F& fn) {
        std::unique_lock<std::mutex> region(busy_, std::try_to_lock);
        if (!region.owns_lock()) return false;
        {
            std::lock_guard<std::mutex> lk(m_);
            while ((int)started_ < nt - 1) {
                const int id = started_ + 1;
                std::thread([this, id]() { work(id); }).detach();
                ++started_;
            }
            call_ = [](void* f, int k) { (*static_cast<F*>(f))(k); };
            fn_ = &fn;
            active_ = nt - 1;
            remaining_ = nt - 1;
            ++generation_;
        }
        wake_.notify_all();
        fn(0);
        std::unique_lock<std::mutex> lk(m_);
        done_.wait(lk, [this]() { return remaining_ == 0; });
        return true;
    }

    static WorkerPool& instance() {
        static std::mutex guard;
        static WorkerPool* pool = nullptr;
        static pid_t owner = 0;
        std::lock_guard<std::mutex> lk(guard);
        if (pool == nullptr || owner != getpid()) {  // never freed: its threads may still sleep in it
            pool = new WorkerPool();
            owner = getpid();
        }
        return *pool;
    }

  private:
    void work(int id) {
        int64_t seen = 0;
        std::unique_lock<std::mutex> lk(m_);
        for (;;) {
            wake_.wait(lk, [&]() { return generation_ != seen; });
            seen = generation_;
            if (id > active_) continue;  // not needed in this region
            void (*call)(void*, int) = call_;
            void* fn = fn_;
            lk.unlock();
            {
                FlushDenormals ftz;
                call(fn, id);
            }
            lk.lock();
            if (--remaining_ == 0) done_.notify_one();
        }
    }

    std::mutex busy_, m_;
    std::condition_variable wake_, done_;
    int started_ = 0, active_ = 0, remaining_ = 0;
    int64_t generation_ = 0;
    void (*call_)(void*, int) = nullptr;
    void* fn_ = nullptr;
};

// fn(k) for k = 0 .. nt - 1 on nt threads: the pool's workers, or fresh threads while the pool is busy
template <typename F>
static void run_threads(int nt, F fn) {
    if (nt <= 1) { fn(0); return; }
    if (WorkerPool::instance().run(nt, fn)) return;
    std::vector<std::thread> extra;
    for (int k = 1; k < nt; ++k) extra.emplace_back([&fn, k]() { FlushDenormals ftz; fn(k); });
    fn(0);
    for (auto& th : extra) th.join();
}

// static block partition of [0, n) over nt threads (no OpenMP: it would spin against torch's own pool)
// min_n: below this many items one thread does it all (thread hand-off costs more than small work)
template <typename F>
static void parallel_for(int64_t n, int nt, F fn, int64_t min_n = 4096) {
    if (nt < 1) nt = 1;
    if (n < min_n || n < nt || nt == 1) { fn((int64_t)0, n, 0); return; }
    run_threads(nt, [&](int k) { fn(n * k / nt, n * (k + 1) / nt, k); });
}

// tasks 0 .. ntasks-1 over nt threads, handed out one at a time (uneven tasks stay balanced)
template <typename F>
static void parallel_tasks(int64_t ntasks, int nt, F fn) {
    if (nt < 1) nt = 1;
    if (nt > ntasks) nt = (int)ntasks;
    if (nt <= 1) { for (int64_t t = 0; t < ntasks; ++t) fn(t); return; }
    std::atomic<int64_t> next(0);
    run_threads(nt, [&](int) { for (int64_t t; (t = next.fetch_add(1)) < ntasks;) fn(t); });
}

// Scatters partitioned by output band (the voxelizer forward's slabs): the output's outer axis is cut into bands of
// 2^shift indices, and every Gaussian is listed under each band its extent [first, last] (outer indices, inclusive)
// meets. A band is written by one thread only, and within a band the Gaussians come in index order, so every output
// element is summed in Gaussian order whatever the thread count: no per-thread copies of the output, no reduction,
// results identical for 1 and many threads (one thread walks the Gaussians directly: banded_scatter).
struct Bands {
    int shift = 0;
    int64_t count = 0;
    std::vector<int64_t> offset;  // band b's Gaussians are ids[offset[b] .. offset[b + 1])
    std::vector<int32_t> ids;
    std::vector<int64_t> counts;  // scratch of the counting sort
};

// Builds the band lists with a two-pass counting sort over blocks of Gaussians (parallel, index order kept).
// extent(i, &first, &last) returns false for a Gaussian that writes nothing. The lists live in storage of the
// calling thread, reused by its next call (no fresh pages to fault in per call), valid until that thread calls again.
template <typename E>
static const Bands& band_lists(int64_t n, int64_t outer, int nt, E extent) {
    thread_local Bands storage;
    Bands& B = storage;  // a local reference: the worker lambdas below must see the caller's lists, not their own
    // about 4 bands per thread: enough for a dense middle of the image not to leave threads idle, few enough that
    // most Gaussians fall in one band (a Gaussian that spans two is set up twice)
    const int64_t want = std::max<int64_t>(1, std::min<int64_t>(4 * (int64_t)std::max(nt, 1), outer));
    const int64_t rows = (outer + want - 1) / want;  // at least this many indices a band, rounded up to 2^shift
    int shift = 0;
    while (((int64_t)1 << shift) < rows) ++shift;
    const int64_t count = (outer + ((int64_t)1 << shift) - 1) >> shift;
    B.shift = shift;
    B.count = count;
    const int nb = (int)std::max<int64_t>(1, std::min<int64_t>(nt, n / 4096));
    B.counts.assign((size_t)nb * (size_t)count, 0);
    int64_t* counts = B.counts.data();
    auto range = [=](int64_t i, int64_t& b0, int64_t& b1) {
        int64_t f, l;
        if (!extent(i, f, l) || l < f) return false;
        b0 = std::max<int64_t>(0, f >> shift);
        b1 = std::min<int64_t>(count - 1, l >> shift);
        return b1 >= b0;
    };
    // each block counts into its own vector (blocks' counters side by side in one array would share cache lines)
    parallel_tasks(nb, nb, [=](int64_t k) {
        std::vector<int64_t> c((size_t)count, 0);
        for (int64_t i = n * k / nb, e = n * (k + 1) / nb; i < e; ++i) {
            int64_t b0, b1;
            if (range(i, b0, b1))
                for (int64_t b = b0; b <= b1; ++b) ++c[(size_t)b];
        }
        std::copy(c.begin(), c.end(), counts + k * count);
    });
    // positions: band-major, then block (blocks hold ascending Gaussian indices)
    B.offset.assign((size_t)count + 1, 0);
    int64_t pos = 0;
    for (int64_t b = 0; b < count; ++b) {
        B.offset[(size_t)b] = pos;
        for (int k = 0; k < nb; ++k) {
            const int64_t cnt = counts[k * count + b];
            counts[k * count + b] = pos;
            pos += cnt;
        }
    }
    B.offset[(size_t)count] = pos;
    if (B.ids.size() < (size_t)pos) B.ids.resize((size_t)pos);  // grows only: no refill of pages already touched
    int32_t* ids = B.ids.data();
    parallel_tasks(nb, nb, [=](int64_t k) {
        std::vector<int64_t> c(counts + k * count, counts + (k + 1) * count);
        for (int64_t i = n * k / nb, e = n * (k + 1) / nb; i < e; ++i) {
            int64_t b0, b1;
            if (range(i, b0, b1))
                for (int64_t b = b0; b <= b1; ++b) ids[c[(size_t)b]++] = (int32_t)i;
        }
    });
    return B;
}

// body(i, r0, r1) adds Gaussian i's values on outer indices [r0, r1) of the output. One thread: every Gaussian in
// index order over the whole output; several: bands (band_lists) handed out to nt threads.
template <typename E, typename F>
static void banded_scatter(int64_t n, int64_t outer, int nt, E extent, F body_inline) {
    // one out-of-line copy of the body for both paths: with -ffast-math, two inlined copies may be compiled to
    // differently rounded code, and the sums must not depend on the thread count
    auto body = [&body_inline](int64_t i, int64_t r0, int64_t r1) __attribute__((noinline)) {
        body_inline(i, r0, r1);
    };
    if (nt <= 1) {
        for (int64_t i = 0; i < n; ++i) {
            int64_t f, l;
            if (extent(i, f, l) && l >= f) body(i, (int64_t)0, outer);
        }
        return;
    }
    const Bands& bands = band_lists(n, outer, nt, extent);
    const int64_t* off = bands.offset.data();
    const int32_t* ids = bands.ids.data();
    const int shift = bands.shift;
    parallel_tasks(bands.count, nt, [=](int64_t b) {
        const int64_t r0 = b << shift, r1 = std::min(outer, (b + 1) << shift);
        for (int64_t q = off[b]; q < off[b + 1]; ++q) body((int64_t)ids[q], r0, r1);
    });
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
