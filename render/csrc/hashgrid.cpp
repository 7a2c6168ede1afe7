// Multiresolution hash encoding on the CPU: forward and backward as plain loops over points
// (forward, position gradient) or over levels (table gradient: levels own disjoint table rows,
// so threads never write the same row). The index and weight rules are those of
// render/hashgrid.py, which stays the reference (tests compare both).
//
// Built by render/native.py with the system C++ compiler and called through ctypes on raw
// float32/int64 buffers; no torch headers, so it builds in about a second.

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <thread>
#include <vector>

namespace {

constexpr uint32_t kPrime1 = 2654435761u;
constexpr uint32_t kPrime2 = 805459861u;

struct Level {
    float res;         // cells per axis
    int64_t stride1;   // dense: R + 1
    int64_t offset;    // first table row of the level
    bool dense;        // dense indexing (no hash)
};

struct Corners {
    int64_t row[8];    // table rows, corner = x + 2y + 4z
    float w[8];        // trilinear weights
    float frac[3];     // position in the cell
};

inline void corners(const float* x, const Level& lv, uint32_t mask, Corners& c) {
    // x is in [0, 1] (the caller clamps), so truncation is floor. `inside` keeps the rows in
    // the table even for NaN/inf positions, whose NaN weights then reach the loss.
    int64_t cell[3];
    for (int k = 0; k < 3; ++k) {
        const float pos = x[k] * lv.res;
        const float inside = pos >= 0.0f ? std::min(pos, lv.res) : 0.0f;
        const float c0 = std::min(static_cast<float>(static_cast<int64_t>(inside)), lv.res - 1.0f);
        c.frac[k] = pos - c0;
        cell[k] = static_cast<int64_t>(c0);
    }
    // Per-axis parts of the row for the lower (0) and upper (1) corner, combined below.
    int64_t ax[2], ay[2], az[2];
    if (lv.dense) {
        const int64_t sy = lv.stride1, sz = lv.stride1 * lv.stride1;
        ax[0] = cell[0], ax[1] = cell[0] + 1;
        ay[0] = cell[1] * sy, ay[1] = ay[0] + sy;
        az[0] = cell[2] * sz, az[1] = az[0] + sz;
    } else {
        const uint32_t hx = static_cast<uint32_t>(cell[0]);
        const uint32_t hy = static_cast<uint32_t>(cell[1]) * kPrime1;
        const uint32_t hz = static_cast<uint32_t>(cell[2]) * kPrime2;
        ax[0] = hx, ax[1] = hx + 1u;
        ay[0] = hy, ay[1] = static_cast<uint32_t>(hy + kPrime1);
        az[0] = hz, az[1] = static_cast<uint32_t>(hz + kPrime2);
    }
    const float wx[2] = {1.0f - c.frac[0], c.frac[0]};
    const float wy[2] = {1.0f - c.frac[1], c.frac[1]};
    const float wz[2] = {1.0f - c.frac[2], c.frac[2]};
    for (int corner = 0; corner < 8; ++corner) {
        const int bx = corner & 1, by = (corner >> 1) & 1, bz = (corner >> 2) & 1;
        int64_t row;
        if (lv.dense) {
            row = ax[bx] + ay[by] + az[bz];
        } else {
            row = static_cast<int64_t>(
                (static_cast<uint32_t>(ax[bx]) ^ static_cast<uint32_t>(ay[by]) ^
                 static_cast<uint32_t>(az[bz])) & mask);
        }
        c.row[corner] = row + lv.offset;
        c.w[corner] = wz[bz] * wy[by] * wx[bx];
    }
}

std::vector<Level> make_levels(int n_levels, const int64_t* res, const int64_t* offsets,
                               const uint8_t* dense) {
    std::vector<Level> levels(n_levels);
    for (int l = 0; l < n_levels; ++l) {
        levels[l] = {static_cast<float>(res[l]), res[l] + 1, offsets[l], dense[l] != 0};
    }
    return levels;
}

template <typename Fn>
void parallel_for(int64_t n, int n_threads, Fn fn) {
    n_threads = static_cast<int>(std::max<int64_t>(1, std::min<int64_t>(n_threads, n)));
    if (n_threads == 1) {
        fn(0, n);
        return;
    }
    std::vector<std::thread> pool;
    int64_t chunk = (n + n_threads - 1) / n_threads;
    for (int t = 1; t < n_threads; ++t) {
        int64_t lo = t * chunk, hi = std::min(n, lo + chunk);
        if (lo < hi) pool.emplace_back(fn, lo, hi);
    }
    fn(0, std::min(n, chunk));
    for (auto& th : pool) th.join();
}

}  // namespace

extern "C" {

// x01 [N, 3] in [0, 1]; table [T, F]; out [N, L, F].
void hash_encode_forward(const float* x01, int64_t n, const float* table, int64_t n_feat,
                         int64_t n_levels, const int64_t* res, const int64_t* offsets,
                         const uint8_t* dense, int64_t log2_table, float* out, int64_t n_threads) {
    const auto levels = make_levels(static_cast<int>(n_levels), res, offsets, dense);
    const uint32_t mask = static_cast<uint32_t>((int64_t{1} << log2_table) - 1);
    parallel_for(n, static_cast<int>(n_threads), [&](int64_t lo, int64_t hi) {
        Corners c;
        for (int64_t l = 0; l < n_levels; ++l) {  // level-major: its rows stay in cache
            for (int64_t i = lo; i < hi; ++i) {
                corners(x01 + 3 * i, levels[l], mask, c);
                float* o = out + (i * n_levels + l) * n_feat;
                for (int64_t f = 0; f < n_feat; ++f) o[f] = 0.0f;
                for (int k = 0; k < 8; ++k) {
                    const float* t = table + c.row[k] * n_feat;
                    for (int64_t f = 0; f < n_feat; ++f) o[f] += c.w[k] * t[f];
                }
            }
        }
    });
}

// grad_out [N, L, F] -> grad_table [T, F] (accumulated into; the caller zeroes it).
// Threads split the levels (disjoint rows), each walking every point.
void hash_encode_backward_table(const float* x01, int64_t n, int64_t n_feat, int64_t n_levels,
                                const int64_t* res, const int64_t* offsets, const uint8_t* dense,
                                int64_t log2_table, const float* grad_out, float* grad_table,
                                int64_t n_threads) {
    const auto levels = make_levels(static_cast<int>(n_levels), res, offsets, dense);
    const uint32_t mask = static_cast<uint32_t>((int64_t{1} << log2_table) - 1);
    const int64_t threads = std::max<int64_t>(1, std::min(n_threads, n_levels));
    auto work = [&](int64_t first_level) {
        Corners c;
        for (int64_t l = first_level; l < n_levels; l += threads) {
            for (int64_t i = 0; i < n; ++i) {
                corners(x01 + 3 * i, levels[l], mask, c);
                const float* g = grad_out + (i * n_levels + l) * n_feat;
                for (int k = 0; k < 8; ++k) {
                    float* gt = grad_table + c.row[k] * n_feat;
                    for (int64_t f = 0; f < n_feat; ++f) gt[f] += c.w[k] * g[f];
                }
            }
        }
    };
    std::vector<std::thread> pool;
    for (int64_t t = 1; t < threads; ++t) pool.emplace_back(work, t);
    work(0);
    for (auto& th : pool) th.join();
}

// grad_out [N, L, F] -> grad_x01 [N, 3] (overwritten): the derivative of the trilinear weights.
void hash_encode_backward_x(const float* x01, int64_t n, const float* table, int64_t n_feat,
                            int64_t n_levels, const int64_t* res, const int64_t* offsets,
                            const uint8_t* dense, int64_t log2_table, const float* grad_out,
                            float* grad_x, int64_t n_threads) {
    const auto levels = make_levels(static_cast<int>(n_levels), res, offsets, dense);
    const uint32_t mask = static_cast<uint32_t>((int64_t{1} << log2_table) - 1);
    parallel_for(n, static_cast<int>(n_threads), [&](int64_t lo, int64_t hi) {
        Corners c;
        for (int64_t i = lo; i < hi; ++i) {
            float gx[3] = {0.0f, 0.0f, 0.0f};
            for (int64_t l = 0; l < n_levels; ++l) {
                corners(x01 + 3 * i, levels[l], mask, c);
                const float* g = grad_out + (i * n_levels + l) * n_feat;
                float s[8];  // d out / d w per corner
                for (int k = 0; k < 8; ++k) {
                    const float* t = table + c.row[k] * n_feat;
                    float acc = 0.0f;
                    for (int64_t f = 0; f < n_feat; ++f) acc += t[f] * g[f];
                    s[k] = acc;
                }
                const float fx = c.frac[0], fy = c.frac[1], fz = c.frac[2];
                float wx[2] = {1.0f - fx, fx}, wy[2] = {1.0f - fy, fy}, wz[2] = {1.0f - fz, fz};
                float dx = 0.0f, dy = 0.0f, dz = 0.0f;
                for (int a = 0; a < 2; ++a) {
                    for (int b = 0; b < 2; ++b) {
                        // corner index = x + 2y + 4z
                        dx += (s[1 + 2 * a + 4 * b] - s[0 + 2 * a + 4 * b]) * wy[a] * wz[b];
                        dy += (s[2 + a + 4 * b] - s[0 + a + 4 * b]) * wx[a] * wz[b];
                        dz += (s[4 + a + 2 * b] - s[0 + a + 2 * b]) * wx[a] * wy[b];
                    }
                }
                gx[0] += dx * levels[l].res;
                gx[1] += dy * levels[l].res;
                gx[2] += dz * levels[l].res;
            }
            for (int k = 0; k < 3; ++k) grad_x[3 * i + k] = gx[k];
        }
    });
}

}  // extern "C"
