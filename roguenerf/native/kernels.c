/* Fused CPU inference kernels for roguenerf (see roguenerf/native/__init__.py).
 *
 * Each kernel does in one pass over the image what the torch fast path does in ten to thirty
 * elementwise passes, with the same float32 operations in the same order where it matters for
 * a decision (projection, inside/visibility tests). Layouts: "channels-last" images are
 * (B, H, W, C) contiguous, i.e. torch's (B, C, H, W) in channels_last memory format.
 * Compiled with -ffp-contract=off so that a * b + c is two roundings, as in torch's unfused
 * elementwise operations. Forward only, float32, no gradient.
 */
#include <math.h>
#if defined(__x86_64__) || defined(__i386__)
#include <immintrin.h>
#endif
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#define RG_API __attribute__((visibility("default")))

static inline float clampf(float v, float lo, float hi) {
    /* torch.clamp: NaN stays NaN */
    return v < lo ? lo : (v > hi ? hi : v);
}

/* Vectors of the CPU's own width, VW float lanes: 16 where the compiler targets AVX-512, 8 with
 * AVX, else 4 (SSE, NEON: the build without -march=native).
 * No wider vector is used: under AVX2, GCC lowers a comparison of 16-lane vectors to a scalar
 * compare and move per lane, and even a scalar broadcast into one goes lane by lane through
 * memory, which made 16-lane kernels several times slower than the torch path on AVX2
 * machines. The results do not depend on VW: every lane does the same float32 operations. */
#if defined(__AVX512F__)
#define VW 16
#elif defined(__AVX__)
#define VW 8
#else
#define VW 4
#endif
typedef float vec __attribute__((vector_size(VW * 4)));
typedef int32_t veci __attribute__((vector_size(VW * 4)));

static inline vec ldv(const float *p) { vec v; memcpy(&v, p, sizeof(v)); return v; }
static inline void stv(float *p, vec v) { memcpy(p, &v, sizeof(v)); }
static inline vec selv(veci m, vec a, vec b) { return (vec)((m & (veci)a) | (~m & (veci)b)); }

/* exp(x), VW lanes: Cephes' expf (range reduction by ln 2, degree-6 polynomial; about 1 ulp),
 * x clamped to [-87, 88] (the result stays a normal float). A macro, so that the window
 * attention below gets its own copy compiled with its floating-point options (GCC does not
 * inline across different ones). */
#define DEFINE_EXPV(name, sel)                                                             \
    static inline vec name(vec x) {                                                        \
        const vec zero = {0}, lo = zero - 87.0f, hi = zero + 88.0f;                        \
        x = sel(x < lo, lo, x);                                                            \
        x = sel(x > hi, hi, x);                                                            \
        const vec y = x * 1.44269504088896341f + 0.5f;                                     \
        vec n = __builtin_convertvector(__builtin_convertvector(y, veci), vec);            \
        n = n + __builtin_convertvector(n > y, vec); /* floor: -1 where n > y */           \
        vec r = x - n * 0.693359375f;                                                      \
        r = r - n * -2.12194440e-4f;                                                       \
        vec p = r * 1.9875691500e-4f + 1.3981999507e-3f;                                   \
        p = p * r + 8.3334519073e-3f;                                                      \
        p = p * r + 4.1665795894e-2f;                                                      \
        p = p * r + 1.6666665459e-1f;                                                      \
        p = p * r + 5.0000001201e-1f;                                                      \
        p = p * (r * r) + r + 1.0f;                                                        \
        const veci bits = (__builtin_convertvector(n, veci) + 127) << 23;                  \
        vec scale;                                                                         \
        memcpy(&scale, &bits, sizeof(scale));                                              \
        return p * scale;                                                                  \
    }

DEFINE_EXPV(expv, selv)

/* Weighted sum of four source rows of C channels into out (tap order as the torch path). */
static inline void taps4(float *restrict out, const float *restrict s00, const float *restrict s10,
                         const float *restrict s01, const float *restrict s11,
                         float w00, float w10, float w01, float w11, int64_t C) {
    int64_t c = 0;
    for (; c + VW <= C; c += VW) {  /* VW channels at a time: the same operations per channel */
        vec acc = ldv(s00 + c) * w00;
        acc = acc + ldv(s10 + c) * w10;
        acc = acc + ldv(s01 + c) * w01;
        acc = acc + ldv(s11 + c) * w11;
        stv(out + c, acc);
    }
    if (c < C && C >= VW) {  /* the last VW channels again: the same operations, the same values */
        c = C - VW;
        vec acc = ldv(s00 + c) * w00;
        acc = acc + ldv(s10 + c) * w10;
        acc = acc + ldv(s01 + c) * w01;
        acc = acc + ldv(s11 + c) * w11;
        stv(out + c, acc);
        return;
    }
    for (; c < C; ++c) {
        float acc = w00 * s00[c];
        acc = acc + w10 * s10[c];
        acc = acc + w01 * s01[c];
        acc = acc + w11 * s11[c];
        out[c] = acc;
    }
}

/* Reprojection of one neighbour into B targets (roguenerf.geometry.reproject, fast path).
 *
 * depth   (B, H, W)       target z-depth
 * rows    (B, 3, H)       per-row term of x numerator, y numerator, z: M_i1 * (v + .5) + M_i2
 * cols    (B, 3, W)       per-column term M_i0 * (u + .5)
 * cvec    (B, 3)          translation term
 * src     (B, Hs, Ws, Cs) sampling source: C features, known depth, known mask (Cs = C + 2)
 * out     (B, H, W, Cs)   features * valid, depth D_{i->k} (0 where invalid), valid (0/1)
 * coords  (B, H, W, 2)    projected (x, y), 0 where not in front
 * lenient = 1 + leniency (float32, as torch multiplies it)
 */
RG_API void rg_reproject(const float *depth, const float *rows, const float *cols, const float *cvec,
                         const float *src, float *out, float *coords,
                         int64_t B, int64_t H, int64_t W, int64_t Hs, int64_t Ws, int64_t Cs,
                         float eps, float max_depth, float lenient, int nthreads) {
    const int64_t C = Cs - 2;
    const float xmax = (float)((double)Ws - 0.5), ymax = (float)((double)Hs - 0.5);
    const float xb = (float)(Ws - 1), yb = (float)(Hs - 1);
    const vec zero = {0};
#pragma omp parallel for collapse(2) schedule(static) num_threads(nthreads)
    for (int64_t b = 0; b < B; ++b) {
        for (int64_t v = 0; v < H; ++v) {
            const float *rw = rows + b * 3 * H;
            const float *cl = cols + b * 3 * W;
            const float *cv = cvec + b * 3;
            const float *sb = src + b * Hs * Ws * Cs;
            const float *drow = depth + (b * H + v) * W;
            float *orow = out + (b * H + v) * W * Cs;
            float *crow = coords + (b * H + v) * W * 2;
            /* The per-pixel arithmetic VW pixels at a time (the same float32 operations, lane by
             * lane), then the sampling and visibility test pixel by pixel. */
            for (int64_t u0 = 0; u0 < W; u0 += VW) {
                const int64_t n = W - u0 < VW ? W - u0 : VW;
                float dv[VW] = {0}, c0[VW] = {0}, c1[VW] = {0}, c2[VW] = {0};
                memcpy(dv, drow + u0, (size_t)n * sizeof(float));
                memcpy(c0, cl + u0, (size_t)n * sizeof(float));
                memcpy(c1, cl + W + u0, (size_t)n * sizeof(float));
                memcpy(c2, cl + 2 * W + u0, (size_t)n * sizeof(float));
                const vec d = ldv(dv);
                const veci known = ((d - d) == 0.0f) & (d > eps) & (d < max_depth);  /* finite, in range */
                const vec z = selv(known, d, zero + 1.0f);
                vec zp = (rw[2 * H + v] + ldv(c2)) * z + cv[2];
                vec x = (rw[v] + ldv(c0)) * z + cv[0];
                vec y = (rw[H + v] + ldv(c1)) * z + cv[1];
                const veci front = ((x - x) == 0.0f) & ((y - y) == 0.0f) & ((zp - zp) == 0.0f) & (zp > eps);
                zp = selv(front, zp, zero + 1.0f);
                x = selv(front, x, zero);
                y = selv(front, y, zero);
                x = x / zp - 0.5f;
                y = y / zp - 0.5f;
                x = selv(front, x, zero);
                y = selv(front, y, zero);
                const veci ok = known & front & (x >= -0.5f) & (x <= xmax) & (y >= -0.5f) & (y <= ymax);
                /* bilinear, border padding: clamp (lanes that are not ok are never read) */
                vec sx = selv(x < 0.0f, zero, x), sy = selv(y < 0.0f, zero, y);
                sx = selv(sx > xb, zero + xb, sx);
                sy = selv(sy > yb, zero + yb, sy);
                sx = selv(ok, sx, zero);
                sy = selv(ok, sy, zero);
                const veci xi = __builtin_convertvector(sx, veci), yi = __builtin_convertvector(sy, veci);
                const vec wx1 = sx - __builtin_convertvector(xi, vec), wy1 = sy - __builtin_convertvector(yi, vec);
                const vec wx0 = 1.0f - wx1, wy0 = 1.0f - wy1;
                float xs[VW], ys[VW], zs[VW], w00[VW], w10[VW], w01[VW], w11[VW];
                int32_t oks[VW], x0s[VW], y0s[VW];
                stv(xs, x); stv(ys, y); stv(zs, zp);
                stv(w00, wx0 * wy0); stv(w10, wx1 * wy0); stv(w01, wx0 * wy1); stv(w11, wx1 * wy1);
                memcpy(oks, &ok, sizeof oks); memcpy(x0s, &xi, sizeof x0s); memcpy(y0s, &yi, sizeof y0s);
                for (int64_t p = 0; p < n; ++p) {
                    const int64_t u = u0 + p;
                    float *o = orow + u * Cs;
                    crow[2 * u] = xs[p];
                    crow[2 * u + 1] = ys[p];
                    if (!oks[p]) {
                        memset(o, 0, (size_t)Cs * sizeof(float));
                        continue;
                    }
                    const int64_t xa = x0s[p], ya = y0s[p];
                    const int64_t xc = xa + 1 < Ws ? xa + 1 : Ws - 1, yc = ya + 1 < Hs ? ya + 1 : Hs - 1;
                    taps4(o, sb + (ya * Ws + xa) * Cs, sb + (ya * Ws + xc) * Cs, sb + (yc * Ws + xa) * Cs,
                          sb + (yc * Ws + xc) * Cs, w00[p], w10[p], w01[p], w11[p], Cs);
                    /* visibility */
                    const float weight = o[C + 1];
                    const int seen = weight >= 0.5f;
                    const float zi = o[C] / (seen ? weight : 1.0f);
                    const int visible = zs[p] <= lenient * zi;
                    if (seen && visible) {
                        o[C] = zi;
                        o[C + 1] = 1.0f;
                    } else {
                        memset(o, 0, (size_t)Cs * sizeof(float));
                    }
                }
            }
        }
    }
}

/* Where output index i of an 8x bilinear upsampling (align_corners=False) reads its input of
 * size n: indices i0, i1 and weights l0, l1 (torch's area_pixel_compute_source_index with
 * scale 1/8, and its index / lambda guards). */
static inline void upsample_source(int64_t i, int64_t n, int64_t *i0, int64_t *i1, float *l0, float *l1) {
    float r = 0.125f * ((float)i + 0.5f) - 0.5f;
    if (r < 0.0f) r = 0.0f;
    int64_t k = (int64_t)r;
    if (k > n - 1) k = n - 1;
    float lam = r - (float)k;
    lam = lam < 0.0f ? 0.0f : (lam > 1.0f ? 1.0f : lam);
    *i0 = k;
    *i1 = k < n - 1 ? k + 1 : k;
    *l1 = lam;
    *l0 = 1.0f - lam;
}

/* Flow warp of one neighbour's buffer (roguenerf.models.flow: upsample_flow + flow_warp).
 *
 * src   (B, H, W, Cs)  channels-last buffer to warp (zero padding outside)
 * flow  (B, 2, h, w)   flow at 1/8 resolution, contiguous; upsampled bilinearly
 *                      (align_corners=False, scale 1/8) and times 8, as F.interpolate does
 * out   (B, H, W, Cs)
 * scale (B,) or NULL   if given, channel dchan of the result becomes clamp(v / scale, 0, dmax)
 * Returns the number of non-finite sample coordinates (the caller then uses the torch path;
 * out is not valid).
 */
RG_API int64_t rg_flow_warp(const float *src, const float *flow, float *out,
                            int64_t B, int64_t H, int64_t W, int64_t Cs, int64_t h, int64_t w,
                            const float *scale, int64_t dchan, float dmax, int nthreads) {
    int64_t bad = 0;
#pragma omp parallel for collapse(2) schedule(static) num_threads(nthreads) reduction(+ : bad)
    for (int64_t b = 0; b < B; ++b) {
        for (int64_t v = 0; v < H; ++v) {
            const float *fx = flow + b * 2 * h * w, *fy = fx + h * w;
            const float *sb = src + b * H * W * Cs;
            float *orow = out + (b * H + v) * W * Cs;
            int64_t r0, r1;
            float ly0, ly1;
            upsample_source(v, h, &r0, &r1, &ly0, &ly1);
            for (int64_t u = 0; u < W; ++u) {
                float *o = orow + u * Cs;
                int64_t c0, c1;
                float lx0, lx1;
                upsample_source(u, w, &c0, &c1, &lx0, &lx1);
                const float dx = ly0 * (lx0 * fx[r0 * w + c0] + lx1 * fx[r0 * w + c1])
                                 + ly1 * (lx0 * fx[r1 * w + c0] + lx1 * fx[r1 * w + c1]);
                const float dy = ly0 * (lx0 * fy[r0 * w + c0] + lx1 * fy[r0 * w + c1])
                                 + ly1 * (lx0 * fy[r1 * w + c0] + lx1 * fy[r1 * w + c1]);
                const float x = (float)u + dx * 8.0f, y = (float)v + dy * 8.0f;
                if (!isfinite(x) || !isfinite(y)) {
                    ++bad;
                    memset(o, 0, (size_t)Cs * sizeof(float));
                    continue;
                }
                /* bilinear, zero padding: a tap outside weighs 0 (per axis) */
                const float x0f = floorf(x), y0f = floorf(y);
                float wx1 = x - x0f, wy1 = y - y0f;
                float wx0 = 1.0f - wx1, wy0 = 1.0f - wy1;
                const int64_t x0 = (int64_t)x0f, y0 = (int64_t)y0f;
                if (!(x0 >= 0 && x0 < W)) wx0 = 0.0f;
                if (!(x0 >= -1 && x0 < W - 1)) wx1 = 0.0f;
                if (!(y0 >= 0 && y0 < H)) wy0 = 0.0f;
                if (!(y0 >= -1 && y0 < H - 1)) wy1 = 0.0f;
                {
                    const int64_t xa = x0 < 0 ? 0 : (x0 > W - 1 ? W - 1 : x0);
                    const int64_t xc = x0 + 1 < 0 ? 0 : (x0 + 1 > W - 1 ? W - 1 : x0 + 1);
                    const int64_t ya = y0 < 0 ? 0 : (y0 > H - 1 ? H - 1 : y0);
                    const int64_t yc = y0 + 1 < 0 ? 0 : (y0 + 1 > H - 1 ? H - 1 : y0 + 1);
                    taps4(o, sb + (ya * W + xa) * Cs, sb + (ya * W + xc) * Cs, sb + (yc * W + xa) * Cs,
                          sb + (yc * W + xc) * Cs, wx0 * wy0, wx1 * wy0, wx0 * wy1, wx1 * wy1, Cs);
                }
                if (scale) o[dchan] = clampf(o[dchan] / scale[b], 0.0f, dmax);
            }
        }
    }
    return bad;
}

/* Replicate-padded 8x8 average pool of the first F channels (roguenerf.models.flow._pool).
 *
 * src (B, H, W, Cs) channels-last; out (B, h, w, F) channels-last with h = ceil(H / 8),
 * w = ceil(W / 8): pixels beyond the image repeat the last row / column.
 */
RG_API void rg_pool8(const float *src, float *out, int64_t B, int64_t H, int64_t W, int64_t Cs,
                     int64_t F, int nthreads) {
    const int64_t h = (H + 7) / 8, w = (W + 7) / 8;
#pragma omp parallel for collapse(2) schedule(static) num_threads(nthreads)
    for (int64_t b = 0; b < B; ++b) {
        for (int64_t i = 0; i < h; ++i) {
            float *acc = out + (b * h + i) * w * F;  /* summed in place, then divided */
            memset(acc, 0, (size_t)(w * F) * sizeof(float));
            const float *sb = src + b * H * W * Cs;
            for (int64_t dy = 0; dy < 8; ++dy) {
                int64_t y = i * 8 + dy;
                if (y > H - 1) y = H - 1;
                const float *row = sb + y * W * Cs;
                for (int64_t x = 0; x < w * 8; ++x) {
                    const float *p = row + (x < W ? x : W - 1) * Cs;
                    float *a = acc + (x / 8) * F;
                    for (int64_t c = 0; c < F; ++c) a[c] += p[c];
                }
            }
            for (int64_t k = 0; k < w * F; ++k) acc[k] = acc[k] / 64.0f;
        }
    }
}

/* Pixel attention's second half, the weighting and the max / min pool, for one neighbour
 * (roguenerf.models.enhancer, fast path):
 *   g      = leaky_relu(hidden + term)                      (B, H, W, Hd), computed on the fly
 *   psi    = sigmoid(conv3x3(g, w2) + b2) * cam[b]          zero padding
 *   a      = buf[..., :F] * psi
 *   pooled = a if first else max(pooled, a);  low = a if first else min(low, a)  (NaN propagates)
 * hidden, term (B, H, W, Hd); w2 (Hd, 3, 3) (conv weight (1, Hd, 3, 3)); buf (B, H, W, Cs);
 * pooled, low (B, H, W, F) (low may be NULL).
 */
RG_API int rg_attend_pool(const float *hidden, const float *term, const float *w2, float b2, float slope,
                          const float *cam, const float *buf, float *pooled, float *low,
                          int64_t B, int64_t H, int64_t W, int64_t Hd, int64_t Cs, int64_t F, int first,
                          int nthreads) {
    int failed = 0;
#pragma omp parallel num_threads(nthreads) reduction(| : failed)
    {
        /* per thread: leaky(hidden + term) of rows v-1..v+1, channel-major and zero-padded by one
         * pixel each side, and the row's attention weights (heap: rows may be wide) */
        const int64_t gw = W + 2;
        float *g = malloc(((size_t)(3 * Hd * gw) + (size_t)W) * sizeof(float));
        if (!g) failed = 1;
        float *s = g ? g + 3 * Hd * gw : 0;
        /* image row held by each of the three slots (-1: zeros): consecutive output rows of a
         * thread share two of their three input rows, computed once */
        int64_t have[3] = {-2, -2, -2};
        const float *slot[3];
#pragma omp for collapse(2) schedule(static)
        for (int64_t b = 0; b < B; ++b) {
            for (int64_t v = 0; v < H; ++v) {
                if (!g) continue;
                for (int64_t r = 0; r < 3; ++r) {
                    const int64_t y = v + r - 1, key = (y < 0 || y >= H) ? -1 : b * H + y;
                    const int k = (int)((y + 3) % 3);
                    float *gr = g + k * Hd * gw;
                    slot[r] = gr;
                    if (have[k] == key) continue;
                    have[k] = key;
                    if (key < 0) {
                        memset(gr, 0, (size_t)(Hd * gw) * sizeof(float));
                        continue;
                    }
                    const float *hr = hidden + (b * H + y) * W * Hd, *tr = term + (b * H + y) * W * Hd;
                    for (int64_t c = 0; c < Hd; ++c) {
                        gr[c * gw] = 0.0f;
                        gr[c * gw + W + 1] = 0.0f;
                    }
                    for (int64_t u = 0; u < W; ++u) {
                        for (int64_t c = 0; c < Hd; ++c) {
                            const float t = hr[u * Hd + c] + tr[u * Hd + c];
                            gr[c * gw + u + 1] = t > 0.0f ? t : t * slope;
                        }
                    }
                }
                /* the 3 x 3 conv to one channel, 2 VW pixels at a time in registers (the taps summed
                 * in the same order for every pixel, the tail's included) */
                int64_t ub = 0;
                for (; ub + 2 * VW <= W; ub += 2 * VW) {
                    vec s0 = {0}, s1 = {0};
                    for (int64_t c = 0; c < Hd; ++c)
                        for (int64_t r = 0; r < 3; ++r)
                            for (int64_t dx = 0; dx < 3; ++dx) {
                                const float wt = w2[c * 9 + r * 3 + dx];
                                const float *gr = slot[r] + c * gw + dx + ub;
                                s0 = s0 + wt * ldv(gr);
                                s1 = s1 + wt * ldv(gr + VW);
                            }
                    stv(s + ub, s0);
                    stv(s + ub + VW, s1);
                }
                for (int64_t u = ub; u < W; ++u) s[u] = 0.0f;
                for (int64_t c = 0; c < Hd && ub < W; ++c) {
                    for (int64_t r = 0; r < 3; ++r) {
                        for (int64_t dx = 0; dx < 3; ++dx) {
                            const float wt = w2[c * 9 + r * 3 + dx];
                            const float *gr = slot[r] + c * gw + dx;
                            for (int64_t u = ub; u < W; ++u) s[u] = s[u] + wt * gr[u];
                        }
                    }
                }
                const float cb = cam[b];
                int64_t u0 = 0;
                for (; u0 + VW <= W; u0 += VW) {  /* psi = cam * sigmoid(s + b2), VW pixels at a time */
                    const vec t = ldv(s + u0) + b2;
                    stv(s + u0, cb * (1.0f / (1.0f + expv(-t))));
                }
                for (; u0 < W; ++u0) s[u0] = cb * (1.0f / (1.0f + expf(-(s[u0] + b2))));
                const float *brow = buf + (b * H + v) * W * Cs;
                float *prow = pooled + (b * H + v) * W * F;
                float *lrow = low ? low + (b * H + v) * W * F : 0;
                for (int64_t u = 0; u < W; ++u) {
                    const float psi = s[u];
                    const float *f = brow + u * Cs;
                    float *p = prow + u * F;
                    if (first) {
                        for (int64_t c = 0; c < F; ++c) p[c] = f[c] * psi;
                        if (lrow) memcpy(lrow + u * F, p, (size_t)F * sizeof(float));
                        continue;
                    }
                    float *l = lrow ? lrow + u * F : 0;
                    int64_t c = 0;
                    for (; c + VW <= F; c += VW) {  /* VW channels at a time, as below */
                        const vec a = ldv(f + c) * psi, pc = ldv(p + c);
                        stv(p + c, selv((a > pc) | (a != a), a, pc));
                        if (l) {
                            const vec lc = ldv(l + c);
                            stv(l + c, selv((a < lc) | (a != a), a, lc));
                        }
                    }
                    for (; c < F; ++c) {
                        const float a = f[c] * psi;
                        p[c] = (a > p[c] || isnan(a)) ? a : p[c];
                        if (l) l[c] = (a < l[c] || isnan(a)) ? a : l[c];
                    }
                }
            }
        }
        free(g);
    }
    return failed ? -1 : 0;
}

/* LayerNorm of one C-channel token into out (torch.nn.functional.layer_norm, biased variance).
 * Always inlined: the callers' constant C (8, 16, 32) gives unrolled, vectorised code. */
typedef float ln8 __attribute__((vector_size(32)));

/* Sum of the 8 lanes as a tree, not left to right: a float32 rounding apart from a sequential
 * sum, as torch's own vectorised reductions are. */
static inline float ln_hsum8(ln8 v) {
    float a[8];
    memcpy(a, &v, sizeof a);
    return ((a[0] + a[4]) + (a[2] + a[6])) + ((a[1] + a[5]) + (a[3] + a[7]));
}

static inline __attribute__((always_inline)) void layer_norm_row(const float *restrict x, float *restrict out,
                                                                  const float *w, const float *bias, int64_t C,
                                                                  float eps) {
    if (C % 8 == 0) {  /* 8-lane partial sums: a short dependency chain per token */
        ln8 acc = {0}, v;
        for (int64_t c = 0; c < C; c += 8) {
            memcpy(&v, x + c, sizeof v);
            acc = acc + v;
        }
        const float mean = ln_hsum8(acc) / (float)C;
        ln8 sq = {0};
        for (int64_t c = 0; c < C; c += 8) {
            memcpy(&v, x + c, sizeof v);
            v = v - mean;
            sq = sq + v * v;
        }
        const float rstd = 1.0f / sqrtf(ln_hsum8(sq) / (float)C + eps);
        for (int64_t c = 0; c < C; c += 8) {
            ln8 g, b;
            memcpy(&v, x + c, sizeof v);
            memcpy(&g, w + c, sizeof g);
            memcpy(&b, bias + c, sizeof b);
            v = (v - mean) * rstd * g + b;
            memcpy(out + c, &v, sizeof v);
        }
        return;
    }
    float mean = 0.0f;
    for (int64_t c = 0; c < C; ++c) mean += x[c];
    mean /= (float)C;
    float var = 0.0f;
    for (int64_t c = 0; c < C; ++c) {
        const float d = x[c] - mean;
        var += d * d;
    }
    var /= (float)C;
    const float rstd = 1.0f / sqrtf(var + eps);
    for (int64_t c = 0; c < C; ++c) out[c] = (x[c] - mean) * rstd * w[c] + bias[c];
}

#define LN_ANY(src, dst)                                                             \
    do {                                                                             \
        if (C == 8) layer_norm_row(src, dst, w, bias, 8, eps);                       \
        else if (C == 16) layer_norm_row(src, dst, w, bias, 16, eps);                \
        else if (C == 32) layer_norm_row(src, dst, w, bias, 32, eps);                \
        else layer_norm_row(src, dst, w, bias, C, eps);                              \
    } while (0)

/* Offsets into a (B, H, W, C) image of the win x win tokens of window (wi, wj) of image b after
 * roll(x, (-shift, -shift)): token a * win + c comes from pixel (wi * win + a + shift,
 * wj * win + c + shift) mod (H, W), and the merge's roll by +shift puts it back there. */
static void window_offsets(int64_t *at, int64_t b, int64_t wi, int64_t wj, int64_t H, int64_t W, int64_t C,
                           int64_t win, int64_t shift) {
    for (int64_t a = 0; a < win; ++a) {
        int64_t i = wi * win + a + shift;
        if (i >= H) i -= H;
        int64_t j = wj * win + shift;
        for (int64_t c = 0; c < win; ++c, ++j) {
            if (j >= W) j -= W;
            at[a * win + c] = ((b * H + i) * W + j) * C;
        }
    }
}

/* The first LayerNorm of the n tokens at offsets at[k] of x into dst (n x C), and the way back:
 * x_out = x + y then the second LayerNorm, token k at offset at[k] of x, x_out and normed. Not
 * inlined: rg_lewin_attention below calls them from code compiled with other floating-point
 * options, and they must do the same float32 operations for it as for the split kernels. */
static __attribute__((noinline)) void ln_gather(const float *x, const int64_t *at, int64_t n, float *restrict dst,
                                                const float *w, const float *bias, float eps, int64_t C) {
    for (int64_t k = 0; k < n; ++k) LN_ANY(x + at[k], dst + k * C);
}

static __attribute__((noinline)) void add_ln_scatter(const float *x, const float *restrict y, const int64_t *at,
                                                     int64_t n, float *x_out, float *normed, const float *w,
                                                     const float *bias, float eps, int64_t C) {
    for (int64_t k = 0; k < n; ++k) {
        const float *xs = x + at[k], *ys = y + k * C;
        float *xo = x_out + at[k];
        for (int64_t c = 0; c < C; ++c) xo[c] = xs[c] + ys[c];
        LN_ANY(xo, normed + at[k]);
    }
}

/* LeWin block's first half, before the attention (roguenerf.models.uformer.LeWinBlock):
 * tokens = window_partition(roll(layer_norm(x), (-shift, -shift))).
 * x (B, H, W, C); tokens (B * nh * nw, win * win, C), windows row-major per image. */
RG_API void rg_ln_partition(const float *x, float *tokens, const float *w, const float *bias, float eps,
                            int64_t B, int64_t H, int64_t W, int64_t C, int64_t win, int64_t shift,
                            int nthreads) {
    const int64_t nh = H / win, nw = W / win, L = win * win;
#pragma omp parallel for collapse(2) schedule(static) num_threads(nthreads)
    for (int64_t b = 0; b < B; ++b) {
        for (int64_t wi = 0; wi < nh; ++wi) {
            int64_t at[L];
            for (int64_t wj = 0; wj < nw; ++wj) {
                window_offsets(at, b, wi, wj, H, W, C, win, shift);
                ln_gather(x, at, L, tokens + ((b * nh + wi) * nw + wj) * L * C, w, bias, eps, C);
            }
        }
    }
}

/* The attention's output back into the image, plus the residual, then the second LayerNorm:
 * x_out = x + roll(window_merge(tokens), (shift, shift)); normed = layer_norm(x_out).
 * x, x_out, normed (B, H, W, C); tokens (B * nh * nw, win * win, C). */
RG_API void rg_merge_ln(const float *x, const float *tokens, float *x_out, float *normed, const float *w,
                        const float *bias, float eps, int64_t B, int64_t H, int64_t W, int64_t C, int64_t win,
                        int64_t shift, int nthreads) {
    const int64_t nh = H / win, nw = W / win, L = win * win;
#pragma omp parallel for collapse(2) schedule(static) num_threads(nthreads)
    for (int64_t b = 0; b < B; ++b) {
        for (int64_t wi = 0; wi < nh; ++wi) {
            int64_t at[L];
            for (int64_t wj = 0; wj < nw; ++wj) {
                window_offsets(at, b, wi, wj, H, W, C, win, shift);
                add_ln_scatter(x, tokens + ((b * nh + wi) * nw + wj) * L * C, at, L, x_out, normed, w, bias,
                               eps, C);
            }
        }
    }
}

/* ---- Window attention -------------------------------------------------------------------
 * From here on the compiler may contract a * b + c into a fused multiply-add, as oneDNN's and
 * torch's attention kernels do: these are sums of products whose rounding decides nothing.
 * Helpers are defined again below so that they are compiled (and inlined) with that option. */
#if defined(__clang__)
#pragma clang fp contract(fast)
#elif defined(__GNUC__)
#pragma GCC optimize("fp-contract=fast")
#endif

#define WA_LD(T, p) ({ T _v; memcpy(&_v, (p), sizeof(_v)); _v; })  /* a value, not a stored-to array */
#define WA_LDV(p) WA_LD(vec, p)
typedef float v8f __attribute__((vector_size(32)));

static inline vec wa_sel(veci m, vec a, vec b) { return (vec)((m & (veci)a) | (~m & (veci)b)); }
DEFINE_EXPV(wa_exp, wa_sel)

/* Keys whose scores are summed at once: 16 accumulators fill half of AVX-512's 32 registers,
 * AVX2 has 16 in all, so there the keys go in two passes of 8. */
#define WA_KEYS (VW == 16 ? 16 : 8)

/* One 16-token window and one head of d channels, queries i0 .. i0 + VW - 1:
 * out_i = softmax_j(scale * q_i . k_j + bias_ij [+ mask_ij]) v_j, rows of q, k, v 3C apart.
 * The scores are formed transposed, one vector per key j over the VW queries, so that the
 * softmax's max and sum over j are elementwise across 16 vectors (no horizontal shuffles) and
 * the sums q . k_j are independent chains the CPU overlaps. bt is the bias transposed,
 * bt[j][i] = bias[i][j]; the mask is read transposed. The probabilities go through memory
 * (pt[j][i]) to the value sum, four query rows at a time. */
#define WA_ROWS 4
static inline void wa_block(const float *restrict t, const float *restrict bt, const float *restrict mw,
                            float *restrict oh, int64_t C, int64_t d, float scale, int i0) {
    float qt[64 * VW] __attribute__((aligned(64))), pt[16][VW] __attribute__((aligned(64)));
    for (int i = 0; i < VW; ++i)
        for (int64_t c = 0; c < d; ++c) qt[c * VW + i] = t[(i0 + i) * 3 * C + c];
    vec s[16];
    for (int j0 = 0; j0 < 16; j0 += WA_KEYS) {
        vec acc[WA_KEYS];
        for (int j = 0; j < WA_KEYS; ++j) acc[j] = WA_LDV(qt) * t[(j0 + j) * 3 * C + C];
        for (int64_t c = 1; c < d; ++c) {
            const vec q = WA_LDV(qt + c * VW);
            for (int j = 0; j < WA_KEYS; ++j) acc[j] = acc[j] + q * t[(j0 + j) * 3 * C + C + c];
        }
        for (int j = 0; j < WA_KEYS; ++j) s[j0 + j] = acc[j];
    }
    vec m;
    for (int j = 0; j < 16; ++j) {
        s[j] = s[j] * scale + WA_LDV(bt + j * 16 + i0);
        if (mw) {
            float col[VW] __attribute__((aligned(64)));
            for (int i = 0; i < VW; ++i) col[i] = mw[(i0 + i) * 16 + j];
            s[j] = s[j] + WA_LDV(col);
        }
        m = j ? wa_sel(m > s[j], m, s[j]) : s[j];
    }
    vec sum;
    for (int j = 0; j < 16; ++j) {
        s[j] = wa_exp(s[j] - m);
        sum = j ? sum + s[j] : s[j];
    }
    for (int j = 0; j < 16; ++j) {
        const vec p = s[j] / sum;
        memcpy(pt[j], &p, sizeof(p));
    }
    const float *v = t + 2 * C;
    for (int r0 = 0; r0 < VW; r0 += WA_ROWS) {
        float *o = oh + (i0 + r0) * C;
        int64_t c = 0;
        for (; c + VW <= d; c += VW) {
            vec acc[WA_ROWS];
            const vec v0 = WA_LDV(v + c);
            for (int r = 0; r < WA_ROWS; ++r) acc[r] = v0 * pt[0][r0 + r];
            for (int j = 1; j < 16; ++j) {
                const vec vj = WA_LDV(v + j * 3 * C + c);
                for (int r = 0; r < WA_ROWS; ++r) acc[r] = acc[r] + vj * pt[j][r0 + r];
            }
            for (int r = 0; r < WA_ROWS; ++r) memcpy(o + r * C + c, &acc[r], sizeof(acc[r]));
        }
        for (; c + 8 <= d; c += 8) {
            v8f acc[WA_ROWS], vj;
            memcpy(&vj, v + c, sizeof(vj));
            for (int r = 0; r < WA_ROWS; ++r) acc[r] = vj * pt[0][r0 + r];
            for (int j = 1; j < 16; ++j) {
                memcpy(&vj, v + j * 3 * C + c, sizeof(vj));
                for (int r = 0; r < WA_ROWS; ++r) acc[r] = acc[r] + vj * pt[j][r0 + r];
            }
            for (int r = 0; r < WA_ROWS; ++r) memcpy(o + r * C + c, &acc[r], sizeof(acc[r]));
        }
        for (; c < d; ++c) {
            for (int r = 0; r < WA_ROWS; ++r) {
                float acc = v[c] * pt[0][r0 + r];
                for (int j = 1; j < 16; ++j) acc = acc + v[j * 3 * C + c] * pt[j][r0 + r];
                o[r * C + c] = acc;
            }
        }
    }
}

/* Window multi-head self-attention with a relative position bias and an optional additive shift
 * mask, for 4 x 4 windows (roguenerf.models.uformer.WindowAttention, between its two linears):
 * qkv (WB, 16, 3 * heads * d), channels (three, head, d); bias_t (heads, 16, 16) the bias
 * transposed (bias_t[n][j][i] = bias[n][i][j]); mask (nw, 16, 16)
 * or NULL, window w using mask[w % nw]; out (WB, 16, heads * d). d <= 64. */
RG_API void rg_window_attention16(const float *qkv, const float *bias_t, const float *mask, float *out,
                                  int64_t WB, int64_t nw, int64_t heads, int64_t d, float scale, int nthreads) {
    const int64_t C = heads * d;
#pragma omp parallel for schedule(static) num_threads(nthreads)
    for (int64_t w = 0; w < WB; ++w) {
        const float *t = qkv + w * 16 * 3 * C;
        const float *mw = mask ? mask + (w % nw) * 256 : 0;
        float *o = out + w * 16 * C;
        for (int64_t n = 0; n < heads; ++n)
            for (int i0 = 0; i0 < 16; i0 += VW) wa_block(t + n * d, bias_t + n * 256, mw, o + n * d, C, d, scale, i0);
    }
}

/* out (16 x N) = bias + in (16 x K) @ wt (K x N, row-major): the attention's two linears on one
 * window. N a multiple of 8. Register blocks of NT tokens x NV vectors of type T (L columns; per
 * input channel NV weight loads and NT broadcasts feed NT * NV multiply-adds): 3 vectors of VW
 * columns, then VW-column and (AVX-512) 8-column strips of 8 tokens. */
#define WA_GEMM_BLOCK(T, L, NT, NV)                                                                  \
    static inline void wa_gemm_##L##_##NT##_##NV(const float *restrict in, int64_t K, const float *restrict wt, \
                                                 const float *restrict bias, int64_t N, float *restrict out, \
                                                 int r0, int64_t n0) {                               \
        T acc[NT][NV];                                                                               \
        for (int j = 0; j < NV; ++j) {                                                               \
            const T b = WA_LD(T, bias + n0 + j * L);                                                 \
            for (int r = 0; r < NT; ++r) acc[r][j] = b;                                              \
        }                                                                                            \
        for (int64_t k = 0; k < K; ++k) {                                                            \
            T wv[NV];                                                                                \
            for (int j = 0; j < NV; ++j) wv[j] = WA_LD(T, wt + k * N + n0 + j * L);                  \
            for (int r = 0; r < NT; ++r) {                                                           \
                const float a = in[(r0 + r) * K + k];                                                \
                for (int j = 0; j < NV; ++j) acc[r][j] = acc[r][j] + wv[j] * a;                      \
            }                                                                                        \
        }                                                                                            \
        for (int r = 0; r < NT; ++r)                                                                 \
            for (int j = 0; j < NV; ++j) memcpy(out + (r0 + r) * N + n0 + j * L, &acc[r][j], sizeof(T)); \
    }
#if VW == 16
WA_GEMM_BLOCK(vec, 16, 8, 3)  /* 24 accumulators of AVX-512's 32 registers */
WA_GEMM_BLOCK(vec, 16, 8, 1)
WA_GEMM_BLOCK(v8f, 8, 8, 1)   /* N = 24 or 8 (8 channels): an 8-column strip */
#define WA_NT 8
#define wa_gemm_big wa_gemm_16_8_3
#define wa_gemm_one wa_gemm_16_8_1
#else
WA_GEMM_BLOCK(vec, VW, 4, 3)  /* 12 of AVX2's 16 (## pastes the name VW, not its value) */
WA_GEMM_BLOCK(vec, VW, 8, 1)
#define WA_NT 4
#define wa_gemm_big wa_gemm_VW_4_3
#define wa_gemm_one wa_gemm_VW_8_1
#endif

static inline void wa_gemm16(const float *restrict in, int64_t K, const float *restrict wt,
                             const float *restrict bias, int64_t N, float *restrict out) {
    int64_t n0 = 0;
    for (; n0 + 3 * VW <= N; n0 += 3 * VW)
        for (int r0 = 0; r0 < 16; r0 += WA_NT) wa_gemm_big(in, K, wt, bias, N, out, r0, n0);
    for (; n0 + VW <= N; n0 += VW)
        for (int r0 = 0; r0 < 16; r0 += 8) wa_gemm_one(in, K, wt, bias, N, out, r0, n0);
#if VW == 16
    for (; n0 + 8 <= N; n0 += 8)
        for (int r0 = 0; r0 < 16; r0 += 8) wa_gemm_8_8_1(in, K, wt, bias, N, out, r0, n0);
#endif
}

/* A LeWin block's attention half with 4 x 4 windows, window by window (everything of a window
 * stays in cache; roguenerf.models.uformer.LeWinBlock):
 *   t = window_partition(roll(LN1(x), -shift)); qkv = t Wqkv^T + bqkv;
 *   o = attention(qkv) (rg_window_attention16's wa_block); y = o Wout^T + bout;
 *   x_out = x + roll(window_merge(y), shift); normed = LN2(x_out).
 * A token's rolled position is the pixel it came from, so each window reads and writes only its
 * own 16 pixels. x, x_out, normed (B, H, W, C), H and W multiples of 4, C = heads * d a multiple
 * of 8, d <= 64; wqkv_t (C, 3C) and wout_t (C, C) the linears' weights transposed; bias_t
 * (heads, 16, 16) transposed as rg_window_attention16's; mask (H/4 * W/4, 16, 16) or NULL.
 * Returns -1 when a thread's buffers cannot be allocated. */
RG_API int rg_lewin_attention(const float *x, float *x_out, float *normed, const float *ln1w, const float *ln1b,
                              float eps1, const float *wqkv_t, const float *bqkv, const float *bias_t,
                              const float *mask, const float *wout_t, const float *bout, const float *ln2w,
                              const float *ln2b, float eps2, int64_t B, int64_t H, int64_t W, int64_t C,
                              int64_t heads, int64_t shift, float scale, int nthreads) {
    const int64_t nh = H / 4, nw = W / 4, d = C / heads;
    int failed = 0;
#pragma omp parallel num_threads(nthreads) reduction(| : failed)
    {
        float *t = malloc((size_t)(16 * 6 * C) * sizeof(float));  /* t, qkv (3C), o, y */
        if (!t) failed = 1;
        float *qkv = t ? t + 16 * C : 0, *o = t ? t + 64 * C : 0, *y = t ? t + 80 * C : 0;
#pragma omp for collapse(2) schedule(static)
        for (int64_t b = 0; b < B; ++b) {
            for (int64_t wi = 0; wi < nh; ++wi) {
                if (!t) continue;
                for (int64_t wj = 0; wj < nw; ++wj) {
                    int64_t at[16];
                    window_offsets(at, b, wi, wj, H, W, C, 4, shift);
                    ln_gather(x, at, 16, t, ln1w, ln1b, eps1, C);
                    wa_gemm16(t, C, wqkv_t, bqkv, 3 * C, qkv);
                    const float *mw = mask ? mask + (wi * nw + wj) * 256 : 0;
                    for (int64_t n = 0; n < heads; ++n)
                        for (int i0 = 0; i0 < 16; i0 += VW)
                            wa_block(qkv + n * d, bias_t + n * 256, mw, o + n * d, C, d, scale, i0);
                    wa_gemm16(o, C, wout_t, bout, C, y);
                    add_ln_scatter(x, y, at, 16, x_out, normed, ln2w, ln2b, eps2, C);
                }
            }
        }
        free(t);
    }
    return failed ? -1 : 0;
}

/* ---- LeFF -------------------------------------------------------------------------------
 * The Uformer's locally-enhanced feed-forward with its residual, in one pass over the image:
 *   out = res + W2 gelu(dwconv3x3(gelu(W1 x + b1)) + bdw) + b2
 * (roguenerf.models.uformer.LeFF; dwconv depthwise, zero padding). Each thread walks a band of
 * rows keeping the hidden maps of three rows in a ring (they stay in cache), where oneDNN writes
 * and reads back two full-resolution maps of 4 C channels. Vectors of VW lanes: 16 where the
 * compiler targets AVX-512, else 8 (what the CPU runs natively; more lanes only split). */

/* GELU with the exact erf form, x/2 (1 + erf(x / sqrt 2)); erf by the rational approximation of
 * Eigen and XLA (|error| < 1e-7 on [-4, 4]; erf(+-4) rounds to +-1 in float32, so the argument
 * is clamped there). NaN propagates. */
/* clamp to [-4, 4] with NaN kept: one min and one max instruction where the target has them
 * (x86 min/max return their second operand when either is NaN), else compare and select */
static inline vec lf_clamp4(vec z) {
    const vec zero = {0};
#if defined(__AVX512F__) && VW == 16
    return (vec)_mm512_max_ps((__m512)(zero - 4.0f), _mm512_min_ps((__m512)(zero + 4.0f), (__m512)z));
#elif defined(__AVX__) && VW == 8
    return (vec)_mm256_max_ps((__m256)(zero - 4.0f), _mm256_min_ps((__m256)(zero + 4.0f), (__m256)z));
#else
    z = wa_sel(z > 4.0f, zero + 4.0f, z);
    return wa_sel(z < -4.0f, zero - 4.0f, z);
#endif
}

static inline vec lf_gelu(vec x) {
    const vec z = lf_clamp4(x * 0.70710678118654752f);
    const vec z2 = z * z;
    vec p = z2 * -2.72614225801306e-10f + 2.77068142495902e-08f;
    p = p * z2 + -2.10102402082508e-06f;
    p = p * z2 + -5.69250639462346e-05f;
    p = p * z2 + -7.34990630326855e-04f;
    p = p * z2 + -2.95459980854025e-03f;
    p = p * z2 + -1.60960333262415e-02f;
    vec q = z2 * -1.45660718464996e-05f + -2.13374055278905e-04f;
    q = q * z2 + -1.68282697438203e-03f;
    q = q * z2 + -7.37332916720468e-03f;
    q = q * z2 + -1.42647390514189e-02f;
    const vec h = 0.5f * x;
    return h + h * ((p * z) / q);
}

/* Weights come packed in column tiles (see roguenerf.native.leff): the tile of a (K, N) matrix
 * starting at column n0 with width nt holds column n0 + j of row k at n0 * K + k * nt + j, so a
 * tile's rows are contiguous. Register blocks: NP pixels x NK vectors of L lanes. */

/* dst[p * Hd + k0 + i] = gelu(b1 + x[p] . W1[k0 + i]) for NP pixels and NK * VW hidden channels. */
#define LF_DEFINE_UP(NP, NK)                                                                          \
    static inline void lf_up_##NP##_##NK(const float *restrict x, const float *restrict w1, const float *restrict b1, \
                                         float *restrict dst, int64_t C, int64_t Hd, int64_t k0) {   \
        vec acc[NP][NK];                                                                              \
        for (int j = 0; j < NK; ++j) {                                                                \
            vec b;                                                                                    \
            memcpy(&b, b1 + k0 + VW * j, sizeof b);                                                   \
            for (int p = 0; p < NP; ++p) acc[p][j] = b;                                               \
        }                                                                                             \
        for (int64_t c = 0; c < C; ++c) {                                                             \
            vec w[NK];                                                                                \
            for (int j = 0; j < NK; ++j) memcpy(&w[j], w1 + k0 * C + c * VW * NK + VW * j, sizeof(vec)); \
            for (int p = 0; p < NP; ++p) {                                                            \
                const float xv = x[p * C + c];                                                        \
                for (int j = 0; j < NK; ++j) acc[p][j] += w[j] * xv;                                  \
            }                                                                                         \
        }                                                                                             \
        for (int p = 0; p < NP; ++p)                                                                  \
            for (int j = 0; j < NK; ++j) {                                                            \
                const vec g = lf_gelu(acc[p][j]);                                                     \
                memcpy(dst + p * Hd + k0 + VW * j, &g, sizeof g);                                     \
            }                                                                                         \
    }
LF_DEFINE_UP(6, 2)
LF_DEFINE_UP(1, 2)
LF_DEFINE_UP(6, 1)
LF_DEFINE_UP(1, 1)

/* out[p * C + c0 + i] = b2 + a[p] . W2[c0 + i] (+ res) for NP pixels and NK vectors of type T. */
#define LF_DEFINE_DOWN(T, L, NP, NK)                                                                  \
    static inline void lf_down_##L##_##NP##_##NK(const float *restrict a, const float *restrict w2,  \
                                                 const float *restrict b2, const float *restrict res, \
                                                 float *restrict out, int64_t C, int64_t Hd, int64_t c0) { \
        T acc[NP][NK];                                                                                \
        for (int j = 0; j < NK; ++j) {                                                                \
            T b;                                                                                      \
            memcpy(&b, b2 + c0 + L * j, sizeof b);                                                    \
            for (int p = 0; p < NP; ++p) acc[p][j] = b;                                               \
        }                                                                                             \
        for (int64_t k = 0; k < Hd; ++k) {                                                            \
            T w[NK];                                                                                  \
            for (int j = 0; j < NK; ++j) memcpy(&w[j], w2 + c0 * Hd + k * L * NK + L * j, sizeof(T)); \
            for (int p = 0; p < NP; ++p) {                                                            \
                const float av = a[p * Hd + k];                                                       \
                for (int j = 0; j < NK; ++j) acc[p][j] += w[j] * av;                                  \
            }                                                                                         \
        }                                                                                             \
        for (int p = 0; p < NP; ++p)                                                                  \
            for (int j = 0; j < NK; ++j) {                                                            \
                T r = acc[p][j], q;                                                                   \
                if (res) {                                                                            \
                    memcpy(&q, res + p * C + c0 + L * j, sizeof q);                                   \
                    r = r + q;                                                                        \
                }                                                                                     \
                memcpy(out + p * C + c0 + L * j, &r, sizeof r);                                       \
            }                                                                                         \
    }
#if VW == 16
LF_DEFINE_DOWN(vec, 16, 6, 2)
LF_DEFINE_DOWN(vec, 16, 1, 2)
LF_DEFINE_DOWN(vec, 16, 12, 1)
LF_DEFINE_DOWN(vec, 16, 1, 1)
#else
LF_DEFINE_DOWN(v8f, 8, 6, 2)
LF_DEFINE_DOWN(v8f, 8, 1, 2)
#endif
LF_DEFINE_DOWN(v8f, 8, 12, 1)
LF_DEFINE_DOWN(v8f, 8, 1, 1)

/* One row of W pixels through the first linear + GELU, into dst (W x Hd). Column tiles of 2 VW,
 * then VW (Hd is a multiple of VW). */
static void lf_up_row(const float *restrict x, const float *restrict w1, const float *restrict b1,
                      float *restrict dst, int64_t W, int64_t C, int64_t Hd) {
    int64_t k0 = 0;
    for (; k0 + 2 * VW <= Hd; k0 += 2 * VW) {
        int64_t u = 0;
        for (; u + 6 <= W; u += 6) lf_up_6_2(x + u * C, w1, b1, dst + u * Hd, C, Hd, k0);
        for (; u < W; ++u) lf_up_1_2(x + u * C, w1, b1, dst + u * Hd, C, Hd, k0);
    }
    for (; k0 < Hd; k0 += VW) {
        int64_t u = 0;
        for (; u + 6 <= W; u += 6) lf_up_6_1(x + u * C, w1, b1, dst + u * Hd, C, Hd, k0);
        for (; u < W; ++u) lf_up_1_1(x + u * C, w1, b1, dst + u * Hd, C, Hd, k0);
    }
}

/* a[u] = gelu(bdw + sum over the 3 x 3 taps of wdw * rows), rows[dy] zero-padded by one pixel on
 * each side; pixels in tiles of 8 so that a tile's inputs stay in L1 across the channel loop. */
static void lf_dw_row(const float *const rows[3], const float *restrict wdw, const float *restrict bdw,
                      float *restrict a, int64_t W, int64_t Hd) {
    for (int64_t u0 = 0; u0 < W; u0 += 8) {
        const int64_t u1 = u0 + 8 < W ? u0 + 8 : W;
        for (int64_t k = 0; k < Hd; k += VW) {
            vec w[9], b;
            for (int t = 0; t < 9; ++t) memcpy(&w[t], wdw + t * Hd + k, sizeof(vec));
            memcpy(&b, bdw + k, sizeof b);
            for (int64_t u = u0; u < u1; ++u) {
                vec acc = b, s;
                for (int dy = 0; dy < 3; ++dy)
                    for (int dx = 0; dx < 3; ++dx) {
                        memcpy(&s, rows[dy] + (u + dx) * Hd + k, sizeof s);
                        acc += w[3 * dy + dx] * s;
                    }
                acc = lf_gelu(acc);
                memcpy(a + u * Hd + k, &acc, sizeof acc);
            }
        }
    }
}

#define LF_DOWN_TILES(L, NP, NK, STEP)                                                               \
    for (; c0 + (STEP) <= C; c0 += (STEP)) {                                                         \
        int64_t u = 0;                                                                               \
        for (; u + NP <= W; u += NP)                                                                 \
            lf_down_##L##_##NP##_##NK(a + u * Hd, w2, b2, res ? res + u * C : 0, out + u * C, C, Hd, c0); \
        for (; u < W; ++u) lf_down_##L##_1_##NK(a + u * Hd, w2, b2, res ? res + u * C : 0, out + u * C, C, Hd, c0); \
    }

/* One row through the second linear (+ residual). Column tiles of 32, 16, then 8 with AVX-512,
 * else of 16, then 8. */
static void lf_down_row(const float *restrict a, const float *restrict w2, const float *restrict b2,
                        const float *restrict res, float *restrict out, int64_t W, int64_t C, int64_t Hd) {
    int64_t c0 = 0;
#if VW == 16
    LF_DOWN_TILES(16, 6, 2, 32)
    LF_DOWN_TILES(16, 12, 1, 16)
#else
    LF_DOWN_TILES(8, 6, 2, 16)
#endif
    LF_DOWN_TILES(8, 12, 1, 8)
}

RG_API int rg_vector_width(void) { return VW; }

/* x, res, out (B, H, W, C) (res may be NULL); w1 packed (C, Hd) = W1^T in tiles of 2 VW then VW;
 * b1 (Hd); wdw (9, Hd) tap-major; bdw (Hd); w2 packed (Hd, C) = W2^T in tiles as lf_down_row's;
 * b2 (C). C a multiple of 8, Hd of VW. Returns -1 when a row buffer cannot be allocated. */
RG_API int rg_leff(const float *x, const float *res, float *out, const float *w1, const float *b1,
                   const float *wdw, const float *bdw, const float *w2, const float *b2,
                   int64_t B, int64_t H, int64_t W, int64_t C, int64_t Hd, int nthreads) {
    const int64_t rows = B * H;
    const int64_t bands = nthreads < rows ? (nthreads > 0 ? nthreads : 1) : rows;
    const size_t row = (size_t)(W + 2) * (size_t)Hd;
    int failed = 0;
#pragma omp parallel for schedule(static, 1) num_threads(nthreads) reduction(| : failed)
    for (int64_t band = 0; band < bands; ++band) {
        /* the hidden maps of rows v-1, v, v+1 (zero-padded), then the row after the dwconv */
        float *ring = malloc((3 * row + (size_t)W * (size_t)Hd) * sizeof(float));
        if (!ring) {
            failed = 1;
            continue;
        }
        float *a = ring + 3 * row;
        const int64_t r0 = band * rows / bands, r1 = (band + 1) * rows / bands;
        int64_t have[3] = {-2, -2, -2}; /* which image row each ring slot holds (-1: zeros) */
        for (int64_t rv = r0; rv < r1; ++rv) {
            const int64_t b = rv / H, v = rv % H;
            const float *slot[3];
            for (int dy = 0; dy < 3; ++dy) {
                const int64_t y = v + dy - 1, key = (y < 0 || y >= H) ? -1 : b * H + y;
                const int s = (int)((y + 3) % 3);
                float *buf = ring + s * row;
                if (have[s] != key) {
                    if (key < 0) {
                        memset(buf, 0, row * sizeof(float));
                    } else {
                        memset(buf, 0, (size_t)Hd * sizeof(float));
                        memset(buf + (W + 1) * Hd, 0, (size_t)Hd * sizeof(float));
                        lf_up_row(x + key * W * C, w1, b1, buf + Hd, W, C, Hd);
                    }
                    have[s] = key;
                }
                slot[dy] = buf;
            }
            lf_dw_row(slot, wdw, bdw, a, W, Hd);
            lf_down_row(a, w2, b2, res ? res + rv * W * C : 0, out + rv * W * C, W, C, Hd);
        }
        free(ring);
    }
    return failed ? -1 : 0;
}

/* ---- Small 3 x 3 convolution ------------------------------------------------------------
 * out = conv3x3(x[..., :Cin], weight), zero padding, no bias: the pixel attention's neighbour
 * half (PixelAttention.neighbour_term) and its target half, 17 -> 8 channels, where oneDNN
 * spends twice the FLOP floor. x (B, H, W, Cs) with Cin <= Cs; w (9, Cin, Co) tap-major; bias
 * (Co) or NULL; out (B, H, W, Co), Co a multiple of 8. Blocks of 8 pixels x 8 output channels
 * (one 8-lane accumulator per pixel). */
static inline void c3_block8(const float *restrict x, const float *restrict w, const float *restrict bias,
                             float *restrict out, int64_t H, int64_t W, int64_t Cs, int64_t Cin, int64_t Co,
                             int64_t v, int64_t u, int64_t o) {
    v8f acc[8] = {{0}};
    if (bias) {
        v8f b;
        memcpy(&b, bias + o, sizeof b);
        for (int p = 0; p < 8; ++p) acc[p] = b;
    }
    for (int dy = 0; dy < 3; ++dy) {
        const int64_t y = v + dy - 1;
        if (y < 0 || y >= H) continue;
        for (int dx = 0; dx < 3; ++dx) {
            const float *xr = x + (y * W + u + dx - 1) * Cs;
            const float *wt = w + (dy * 3 + dx) * Cin * Co + o;
            for (int64_t c = 0; c < Cin; ++c) {
                v8f wv;
                memcpy(&wv, wt + c * Co, sizeof wv);
                for (int p = 0; p < 8; ++p) acc[p] += wv * xr[p * Cs + c];
            }
        }
    }
    for (int p = 0; p < 8; ++p) memcpy(out + (v * W + u + p) * Co + o, &acc[p], sizeof acc[p]);
}

static inline void c3_pixel(const float *restrict x, const float *restrict w, const float *restrict bias,
                            float *restrict out, int64_t H, int64_t W, int64_t Cs, int64_t Cin, int64_t Co,
                            int64_t v, int64_t u, int64_t o) {
    v8f acc = {0};
    if (bias) memcpy(&acc, bias + o, sizeof acc);
    for (int dy = 0; dy < 3; ++dy) {
        const int64_t y = v + dy - 1;
        if (y < 0 || y >= H) continue;
        for (int dx = 0; dx < 3; ++dx) {
            const int64_t xx = u + dx - 1;
            if (xx < 0 || xx >= W) continue;
            const float *xp = x + (y * W + xx) * Cs;
            const float *wt = w + (dy * 3 + dx) * Cin * Co + o;
            for (int64_t c = 0; c < Cin; ++c) {
                v8f wv;
                memcpy(&wv, wt + c * Co, sizeof wv);
                acc += wv * xp[c];
            }
        }
    }
    memcpy(out + (v * W + u) * Co + o, &acc, sizeof acc);
}

RG_API void rg_conv3x3(const float *x, const float *w, const float *bias, float *out, int64_t B, int64_t H,
                       int64_t W, int64_t Cs, int64_t Cin, int64_t Co, int nthreads) {
#pragma omp parallel for collapse(2) schedule(static) num_threads(nthreads)
    for (int64_t b = 0; b < B; ++b) {
        for (int64_t v = 0; v < H; ++v) {
            const float *xb = x + b * H * W * Cs;
            float *ob = out + b * H * W * Co;
            for (int64_t o = 0; o < Co; o += 8) {
                int64_t u = 0;
                if (W > 0) c3_pixel(xb, w, bias, ob, H, W, Cs, Cin, Co, v, u++, o);  /* left edge */
                for (; u + 8 <= W - 1; u += 8) c3_block8(xb, w, bias, ob, H, W, Cs, Cin, Co, v, u, o);
                for (; u < W; ++u) c3_pixel(xb, w, bias, ob, H, W, Cs, Cin, Co, v, u, o);
            }
        }
    }
}

/* The normal equations of one damped Gauss-Newton step of the neighbour pose fit
 * (roguenerf.enhance.align, IRLS weights of the Charbonnier penalty), summed over the pixels:
 *   P = R p + t, (u, v) its projection by K, du = dP(u), dv = dP(v) (3-vectors),
 *   ju = [P x du, du], jv = [P x dv, dv],  r_c = s_c - render_c,  w = 1 / sqrt(sum_c r_c^2 + c^2),
 *   A += w (sum gx^2 ju ju^T + sum gx gy (ju jv^T + jv ju^T) + sum gy^2 jv jv^T),
 *   b += w (sum r gx ju + sum r gy jv)                          over the pixels with use > 0.
 * points (N, 3); sampled (9, N): colour, x gradient, y gradient; render (3, N); use (N);
 * pose (3, 4) row-major: [R | t]; K (3, 3) row-major; out (42): A (6 x 6) row-major, then b (6).
 * Summed in double, per thread, then together.
 */
RG_API void rg_gauss_newton(const float *points, const float *sampled, const float *render, const float *use,
                            const float *pose, const float *K, float c, int64_t N, float *out, int nthreads) {
    double A[36] = {0}, b[6] = {0};
#pragma omp parallel num_threads(nthreads)
    {
        double a[36] = {0}, bb[6] = {0};
#pragma omp for schedule(static)
        for (int64_t i = 0; i < N; ++i) {
            if (!(use[i] > 0.0f)) continue;
            const float *p = points + 3 * i;
            double P[3], q[3];
            for (int k = 0; k < 3; ++k)
                P[k] = (double)pose[4 * k] * p[0] + (double)pose[4 * k + 1] * p[1] + (double)pose[4 * k + 2] * p[2]
                       + pose[4 * k + 3];
            for (int k = 0; k < 3; ++k) q[k] = K[3 * k] * P[0] + K[3 * k + 1] * P[1] + K[3 * k + 2] * P[2];
            const double iz = 1.0 / q[2], u = q[0] * iz, v = q[1] * iz;
            double du[3], dv[3];
            for (int k = 0; k < 3; ++k) {
                du[k] = (K[k] - u * K[6 + k]) * iz;
                dv[k] = (K[3 + k] - v * K[6 + k]) * iz;
            }
            const double ju[6] = {P[1] * du[2] - P[2] * du[1], P[2] * du[0] - P[0] * du[2], P[0] * du[1] - P[1] * du[0],
                                  du[0], du[1], du[2]};
            const double jv[6] = {P[1] * dv[2] - P[2] * dv[1], P[2] * dv[0] - P[0] * dv[2], P[0] * dv[1] - P[1] * dv[0],
                                  dv[0], dv[1], dv[2]};
            double rr = 0, gxx = 0, gxy = 0, gyy = 0, rgx = 0, rgy = 0;
            for (int ch = 0; ch < 3; ++ch) {
                const double r = (double)sampled[ch * N + i] - render[ch * N + i];
                const double gx = sampled[(3 + ch) * N + i], gy = sampled[(6 + ch) * N + i];
                rr += r * r;
                gxx += gx * gx;
                gxy += gx * gy;
                gyy += gy * gy;
                rgx += r * gx;
                rgy += r * gy;
            }
            const double w = 1.0 / sqrt(rr + (double)c * c);
            gxx *= w; gxy *= w; gyy *= w; rgx *= w; rgy *= w;
            for (int m = 0; m < 6; ++m) {
                const double xu = gxx * ju[m] + gxy * jv[m], xv = gxy * ju[m] + gyy * jv[m];
                for (int n = 0; n < 6; ++n) a[6 * m + n] += xu * ju[n] + xv * jv[n];
                bb[m] += rgx * ju[m] + rgy * jv[m];
            }
        }
#pragma omp critical
        {
            for (int k = 0; k < 36; ++k) A[k] += a[k];
            for (int k = 0; k < 6; ++k) b[k] += bb[k];
        }
    }
    for (int k = 0; k < 36; ++k) out[k] = (float)A[k];
    for (int k = 0; k < 6; ++k) out[36 + k] = (float)b[k];
}
