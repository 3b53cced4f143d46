// Runs the MPM solver's warp-level CUDA snippets (solvers/mpm_kernels_cuda.py) on a CPU: every lane of a
// warp is a thread and the warp intrinsics they use (__ballot_sync, __match_any_sync, __reduce_max_sync,
// __shfl_sync) are emulated with a barrier.  tests/test_mpm_gpu.py writes the snippets into "snippets.inc"
// (the vector reduction replaced by red4 below) and compiles this file with g++ -std=c++20.
//
// Each trial: random active lanes and stencil keys (random, sorted runs, all distinct, one lane, none),
// 27 nodes per lane with random contributions (multiples of 1/8, so every order of summation is exact).
// Checks: every node receives exactly the sum over the active lanes of its group, in exactly one reduction
// per group and node, and no lane shuffles from a lane outside the active mask.
// Usage: warp_emulation TRIALS   (prints "ok ..." and exits 0, or names the first failure and exits 1)
#include <algorithm>
#include <array>
#include <barrier>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <map>
#include <mutex>
#include <random>
#include <thread>
#include <vector>

#define __CUDA_ARCH__ 900

namespace wp {
template <unsigned N, typename T> struct vec_t {
    T c[N];
    vec_t() {}
    vec_t(T a, T b, T cc, T d) { c[0] = a; c[1] = b; c[2] = cc; c[3] = d; }
    T& operator[](int i) { return c[i]; }
    const T& operator[](int i) const { return c[i]; }
};
using int32 = int;
using float32 = float;
}  // namespace wp

using vec4i = wp::vec_t<4, int>;
using vec4f = wp::vec_t<4, float>;

struct ThreadIndex { unsigned x; };
thread_local ThreadIndex threadIdx;

struct Grid {
    std::map<int, std::array<double, 4>> sums;
    std::map<int, int> reductions;
    std::mutex lock;
};

static void red4(Grid& grid, int index, float a, float b, float c, float d) {
    std::lock_guard<std::mutex> guard(grid.lock);
    auto& s = grid.sums[index];
    s[0] += a; s[1] += b; s[2] += c; s[3] += d;
    grid.reductions[index] += 1;
}

static std::barrier<>* warp_barrier;
static unsigned slot_u[32];
static float slot_f[32];
static unsigned lane_id() { return threadIdx.x & 31u; }

static void fail(const char* what) { std::fprintf(stderr, "%s\n", what); std::exit(1); }

static unsigned __ballot_sync(unsigned mask, bool predicate) {
    slot_u[lane_id()] = predicate;
    warp_barrier->arrive_and_wait();
    unsigned r = 0;
    for (int i = 0; i < 32; ++i)
        if ((mask >> i) & 1u) r |= (slot_u[i] ? 1u : 0u) << i;
    warp_barrier->arrive_and_wait();
    return r;
}

static unsigned __match_any_sync(unsigned mask, int value) {
    if (!((mask >> lane_id()) & 1u)) fail("__match_any_sync called by a lane outside its mask");
    slot_u[lane_id()] = (unsigned)value;
    warp_barrier->arrive_and_wait();
    unsigned r = 0;
    for (int i = 0; i < 32; ++i)
        if (((mask >> i) & 1u) && slot_u[i] == (unsigned)value) r |= 1u << i;
    warp_barrier->arrive_and_wait();
    return r;
}

static unsigned __reduce_max_sync(unsigned mask, unsigned value) {
    slot_u[lane_id()] = value;
    warp_barrier->arrive_and_wait();
    unsigned r = 0;
    for (int i = 0; i < 32; ++i)
        if ((mask >> i) & 1u) r = std::max(r, slot_u[i]);
    warp_barrier->arrive_and_wait();
    return r;
}

static float __shfl_sync(unsigned mask, float value, int source) {
    if (!((mask >> source) & 1u)) fail("__shfl_sync reads a lane outside the mask");
    slot_f[lane_id()] = value;
    warp_barrier->arrive_and_wait();
    float r = slot_f[source];
    warp_barrier->arrive_and_wait();
    return r;
}

static int __popc(unsigned v) { return __builtin_popcount(v); }

#include "snippets.inc"

int main(int argc, char** argv) {
    const int trials = argc > 1 ? std::atoi(argv[1]) : 200;
    const int nodes = 27;
    std::mt19937 rng(12345);
    long checked = 0;
    for (int trial = 0; trial < trials; ++trial) {
        std::array<bool, 32> active;
        std::array<int, 32> key;
        const int nkeys = 1 + (int)(rng() % 12);
        const bool all_active = rng() % 3 == 0;
        for (int l = 0; l < 32; ++l) {
            active[l] = all_active || rng() % 4 != 0;
            key[l] = (int)(rng() % nkeys) * 7 - 3;
        }
        if (trial % 5 == 1) for (int l = 0; l < 32; ++l) key[l] = l / 8;       // freshly sorted: runs of 8
        if (trial % 7 == 2) for (int l = 0; l < 32; ++l) key[l] = 1000 + l;    // all different
        if (trial % 11 == 3) for (int l = 0; l < 32; ++l) active[l] = l == 5;  // a single lane
        if (trial % 13 == 4) for (int l = 0; l < 32; ++l) active[l] = false;   // none (whole padding warp)
        if (trial % 17 == 5) for (int l = 0; l < 32; ++l) { active[l] = true; key[l] = 9; }  // one group of 32
        std::vector<std::array<float, 4>> value(32 * nodes);
        for (auto& v : value)
            for (auto& x : v) x = (float)((int)(rng() % 2001) - 1000) / 8.0f;
        Grid grid;
        std::barrier<> barrier(32);
        warp_barrier = &barrier;
        std::vector<std::thread> lanes;
        for (int l = 0; l < 32; ++l)
            lanes.emplace_back([&, l] {
                threadIdx.x = 64u + (unsigned)l;  // a lane of the third warp of a block
                const vec4i plan = warp_groups(active[l], key[l]);
                if (active[l])
                    for (int n = 0; n < nodes; ++n) {
                        const auto& v = value[l * nodes + n];
                        scatter_warp(grid, key[l] * 100 + n, vec4f(v[0], v[1], v[2], v[3]), plan);
                    }
                barrier.arrive_and_drop();  // the lane returns
            });
        for (auto& t : lanes) t.join();
        std::map<int, std::array<double, 4>> want;
        for (int l = 0; l < 32; ++l)
            if (active[l])
                for (int n = 0; n < nodes; ++n)
                    for (int c = 0; c < 4; ++c) want[key[l] * 100 + n][c] += value[l * nodes + n][c];
        if (want.size() != grid.sums.size()) {
            std::printf("trial %d: %zu nodes received reductions, expected %zu\n", trial, grid.sums.size(), want.size());
            return 1;
        }
        for (const auto& [index, sum] : want) {
            const auto& got = grid.sums[index];
            for (int c = 0; c < 4; ++c)
                if (std::fabs(got[c] - sum[c]) > 1e-9) {
                    std::printf("trial %d node %d component %d: got %g, expected %g\n", trial, index, c, got[c], sum[c]);
                    return 1;
                }
            if (grid.reductions[index] != 1) {
                std::printf("trial %d node %d: %d reductions, expected one per group\n", trial, index,
                            grid.reductions[index]);
                return 1;
            }
            ++checked;
        }
    }
    std::printf("ok: %d trials, %ld node sums exact, one reduction per group and node\n", trials, checked);
    return 0;
}
