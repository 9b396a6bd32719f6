/* Compiled kernel of fiducial_detector.profile_fit, one sampling pass of the edge-profile fit:
 *
 *   sample_lines   the lines on each ellipse and the intensity moments along them
 *                  (profile_fit._lines then profile_fit._centroids, their numpy reference),
 *                  and for an edge printed all round its usable lines, edge positions and
 *                  least-squares sums (profile_fit._edge_terms, the sums of _solve);
 *   normal_sums    the least-squares sums over given lines;
 *   solve_rounds   the fits' two least-squares rounds (Cholesky), the outliers out between;
 *   sample_tracks  the code reader's samples along its elliptical tracks, as cv2.remap gives
 *                  them (the points made here).
 *
 * Why compiled: numpy works a pass as whole (fits x lines x samples) arrays, each a fresh
 * temporary through memory, and cv2.remap needs sample maps built and a float32 copy of the
 * frame; here each fit's lines are made, sampled (from the frame's own 8/16-bit or float32
 * pixels) and reduced while they are in cache, in SIMD, with the next fiducial's pixels
 * prefetched. Bilinear interpolation is exact (cv2.remap rounds positions to 1/32 px). The
 * detection as a whole gains 5-15 %: the rest is OpenCV's contours, the code reader and Python.
 *
 * Only Python.h: arrays come in through the buffer protocol (C-contiguous; sizes checked here,
 * dtypes owned by profile_fit). No GIL is held while working.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <limits.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#define SAMPLES 7
/* Farthest a sample lies from its fit's centre, pixels: larger ellipses are not sampled (no
 * fiducial in a frame of up to 4096 px comes near). */
#define MAX_REACH 4096.0f

/* The per-line loops are built twice, for AVX2 with FMA (x86-64-v3) and for the baseline, and
 * the loader picks the one the CPU runs; noinline keeps each loop whole for the vectoriser. */
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
#define SIMD __attribute__((noinline, target_clones("arch=x86-64-v3", "default")))
#else
#define SIMD __attribute__((noinline))
#endif

/* Moment weights of the forward differences d_j = p_(j+1) - p_j at x_j = j + 1/2: sums of d,
 * d x and d x^2 as weights on the samples (profile_fit._moment_weights). */
static double W[3][SAMPLES];

static void init_weights(void)
{
    for (int p = 0; p < 3; p++) {
        for (int i = 0; i < SAMPLES; i++) W[p][i] = 0.0;
        for (int j = 0; j < SAMPLES - 1; j++) {
            double x = j + 0.5, xp = p == 0 ? 1.0 : (p == 1 ? x : x * x);
            W[p][j + 1] += xp;
            W[p][j] -= xp;
        }
    }
}

/* cos and sin of a small angle (|d| <= 1/2 here: the arc-length correction below) by their
 * series, to ~1e-10. */
static inline void small_cos_sin(double d, double *c, double *s)
{
    double d2 = d * d;
    *c = 1.0 - d2 * (0.5 - d2 * (1.0 / 24 - d2 * (1.0 / 720 - d2 * (1.0 / 40320))));
    *s = d * (1.0 - d2 * (1.0 / 6 - d2 * (1.0 / 120 - d2 * (1.0 / 5040 - d2 * (1.0 / 362880)))));
}

/* One fit's ellipse, in the lines' single precision where the numpy code has it. */
typedef struct {
    double u, v, a, b, angle;
    float cap, pol, lof, hif;
} Fit;

/* Rows of one fit's lines: the outputs (k, m) at the fit's row, and the scratch. */
typedef struct {
    float *kappa, *lower, *upper, *step, *j0, *j1, *j2, *j3, *j4, *mean, *mass, *m2;
    float *cp, *sp, *u0, *v0, *su, *sv, *prof;
    Py_ssize_t stride; /* between the scratch's sample rows */
} Rows;

/* The points spread evenly in arc length to first order (profile_fit._lines): parametric angle
 * phi = psi + e sin(2 psi) / 2 for uniform psi, psi's cos and sin by rotation (no libm call). */
static void angles(const Fit *fit, int n, float *restrict cp, float *restrict sp)
{
    const double ecc = 0.5 * (fit->a - fit->b) / (fit->a + fit->b);
    const double dpsi = 2.0 * M_PI / (double)(n > 0 ? n : 1);
    const double rc = cos(dpsi), rs = sin(dpsi);
    double cpsi = cos(0.5 * dpsi), spsi = sin(0.5 * dpsi);
    for (int l = 0; l < n; l++) {
        double cd, sd;
        small_cos_sin(ecc * 2.0 * spsi * cpsi, &cd, &sd);
        cp[l] = (float)(cpsi * cd - spsi * sd);
        sp[l] = (float)(spsi * cd + cpsi * sd);
        const double c = cpsi * rc - spsi * rs;
        spsi = spsi * rc + cpsi * rs;
        cpsi = c;
    }
}

/* The lines' geometry (profile_fit._lines): no calls, no branches, so that it runs in SIMD. */
SIMD static void geometry(const Fit *fit, int n, const float *restrict cpr, const float *restrict spr,
                     float *restrict kf, float *restrict lf, float *restrict uf,
                     float *restrict sf, float *restrict j0, float *restrict j1,
                     float *restrict j2, float *restrict j3, float *restrict j4,
                     float *restrict u0, float *restrict v0, float *restrict su,
                     float *restrict sv)
{
    const float a = (float)fit->a, bb = (float)fit->b, ang = (float)fit->angle;
    const float ca = cosf(ang), sa = sinf(ang);
    /* The quadratic form Q of the ellipse (edge_fit.quadratic_form), for the jacobian. */
    const double c2 = cos(fit->angle), s2 = sin(fit->angle);
    const double ia = 1.0 / (fit->a * fit->a), ib = 1.0 / (fit->b * fit->b);
    const float qa = (float)(c2 * c2 * ia + s2 * s2 * ib);
    const float qb = (float)(c2 * s2 * (ia - ib));
    const float qc = (float)(s2 * s2 * ia + c2 * c2 * ib);
    const float cap = fit->cap, lof = fit->lof, hif = fit->hif;
    for (int l = 0; l < n; l++) {
        const float cp = cpr[l], sp = spr[l];
        const float lx = a * cp, ly = bb * sp;
        const float nx0 = bb * cp, ny0 = a * sp;
        const float nn = sqrtf(nx0 * nx0 + ny0 * ny0);
        const float nx = nx0 / nn, ny = ny0 / nn;
        const float du = ca * lx - sa * ly, dv = sa * lx + ca * ly;
        const float support = lx * nx + ly * ny;
        kf[l] = a * bb / (nn * nn * nn);
        /* Windows stop half-way to the neighbouring printed edges, and at the cap. */
        const float inner = lof * support, outer = hif * support;
        const float lw = -(inner < cap ? inner : cap);
        const float up = outer < cap ? outer : cap;
        const float width = up - lw;
        lf[l] = lw;
        uf[l] = up;
        sf[l] = width / (SAMPLES - 1);
        const float nu = ca * nx - sa * ny, nv = sa * nx + ca * ny;
        /* d(signed distance)/d(u, v, A, B, C) at the point. */
        const float gx = qa * du + qb * dv, gy = qb * du + qc * dv;
        const float inv = 1.0f / sqrtf(gx * gx + gy * gy);
        j0[l] = gx * -inv;
        j1[l] = gy * -inv;
        j2[l] = du * du * (0.5f * inv);
        j3[l] = du * dv * inv;
        j4[l] = dv * dv * (0.5f * inv);
        /* The window's first sample, relative to the centre, and its span. */
        u0[l] = du + nu * lw;
        v0[l] = dv + nv * lw;
        su[l] = nu * width;
        sv[l] = nv * width;
    }
}

/* One sample of every line (bilinear, borders replicated) from an image of 8 or 16-bit integers
 * or float32 pixels (the integers read as they are: no float copy of the frame, and a quarter
 * of its memory traffic for 8 bits): branch-free gathers that run in
 * SIMD. Positions are relative to the centre's whole pixel (cu, cv), whose fraction (fu, fv)
 * comes from double: float32 resolves them to 1e-5 px (see profile_fit._Lines). */
#define SAMPLER(NAME, TYPE) \
SIMD static void NAME(const TYPE *restrict img, int w, int h, int cu, int cv, float fu, float fv, \
                   float frac, int n, const float *restrict u0, const float *restrict v0, \
                   const float *restrict su, const float *restrict sv, float *restrict out) \
{ \
    const int wm = w - 1, hm = h - 1; \
    for (int l = 0; l < n; l++) { \
        const float x = fu + (u0[l] + su[l] * frac); \
        const float y = fv + (v0[l] + sv[l] * frac); \
        /* floor as the truncation of a positive number: windows lie within MAX_REACH of their \
         * fit's centre (sample_lines leaves larger fits out). */ \
        const int xi = (int)(x + MAX_REACH) - (int)MAX_REACH; \
        const int yi = (int)(y + MAX_REACH) - (int)MAX_REACH; \
        const float ax = x - (float)xi, ay = y - (float)yi; \
        int x0 = xi + cu, y0 = yi + cv; \
        int x1 = x0 + 1, y1 = y0 + 1; \
        x0 = x0 < wm ? x0 : wm; \
        x0 = x0 > 0 ? x0 : 0; \
        x1 = x1 < wm ? x1 : wm; \
        x1 = x1 > 0 ? x1 : 0; \
        y0 = y0 < hm ? y0 : hm; \
        y0 = y0 > 0 ? y0 : 0; \
        y1 = y1 < hm ? y1 : hm; \
        y1 = y1 > 0 ? y1 : 0; \
        const float p00 = (float)img[y0 * w + x0], p01 = (float)img[y0 * w + x1]; \
        const float p10 = (float)img[y1 * w + x0], p11 = (float)img[y1 * w + x1]; \
        const float top = p00 + ax * (p01 - p00), bot = p10 + ax * (p11 - p10); \
        out[l] = top + ay * (bot - top); \
    } \
}

SAMPLER(sample_u8, uint8_t)
SAMPLER(sample_u16, uint16_t)
SAMPLER(sample_f32, float)

/* The compiler does not vectorise gathers of 8 or 16-bit pixels (x86 gathers 32-bit words), so
 * for those the AVX2 loop is written out: each pair of horizontally adjacent pixels from the
 * 32-bit word at the first's byte offset (clamped to the buffer's last word, the pixels then
 * shifted out of it), masked to their width. */
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
#include <immintrin.h>
#define HAVE_AVX2_SAMPLERS 1



/* Two horizontally adjacent pixels (x0, x0 + 1 of one row) from one 32-bit word: the pixel at
 * byte offset off and the next; where x1 == x0 (clamped at the right border) both are the one.
 * Half the gathers of one per pixel. */
__attribute__((target("avx2"))) static inline void gather_pair(const void *img, __m256i off,
                                                               __m256i last, __m256i mask,
                                                               __m256i width_bits, __m256i same,
                                                               __m256 *p0, __m256 *p1)
{
    const __m256i at = _mm256_min_epi32(off, last);
    const __m256i shift = _mm256_slli_epi32(_mm256_sub_epi32(off, at), 3);
    const __m256i word = _mm256_srlv_epi32(_mm256_i32gather_epi32((const int *)img, at, 1), shift);
    const __m256i a = _mm256_and_si256(word, mask);
    const __m256i b = _mm256_and_si256(_mm256_srlv_epi32(word, width_bits), mask);
    *p0 = _mm256_cvtepi32_ps(a);
    *p1 = _mm256_cvtepi32_ps(_mm256_blendv_epi8(b, a, same));
}

/* The frame's constants for bilinear_narrow. */
typedef struct {
    __m256i wm, hm, zero, one, vw, vb, last, mask, bits;
} Narrow;

__attribute__((target("avx2"))) static inline Narrow narrow_frame(int w, int h, int bytes)
{
    Narrow c;
    c.wm = _mm256_set1_epi32(w - 1);
    c.hm = _mm256_set1_epi32(h - 1);
    c.zero = _mm256_setzero_si256();
    c.one = _mm256_set1_epi32(1);
    c.vw = _mm256_set1_epi32(w);
    c.vb = _mm256_set1_epi32(bytes);
    c.last = _mm256_set1_epi32(w * h * bytes - 4);
    c.mask = _mm256_set1_epi32(bytes == 1 ? 0xFF : 0xFFFF);
    c.bits = _mm256_set1_epi32(8 * bytes);
    return c;
}

/* Bilinear samples of eight points whose floor pixels are (gx, gy) and fractions (ax, ay), the
 * corners clamped into the frame. */
__attribute__((target("avx2"))) static inline __m256 bilinear_narrow(const void *img,
                                                                     const Narrow *c, __m256i gx,
                                                                     __m256i gy, __m256 ax,
                                                                     __m256 ay)
{
    const __m256i x0 = _mm256_max_epi32(_mm256_min_epi32(gx, c->wm), c->zero);
    const __m256i x1 = _mm256_max_epi32(_mm256_min_epi32(_mm256_add_epi32(gx, c->one), c->wm), c->zero);
    const __m256i y0 = _mm256_max_epi32(_mm256_min_epi32(gy, c->hm), c->zero);
    const __m256i y1 = _mm256_max_epi32(_mm256_min_epi32(_mm256_add_epi32(gy, c->one), c->hm), c->zero);
    const __m256i r0 = _mm256_mullo_epi32(y0, c->vw), r1 = _mm256_mullo_epi32(y1, c->vw);
    const __m256i same = _mm256_cmpeq_epi32(x0, x1);
    __m256 p00, p01, p10, p11;
    gather_pair(img, _mm256_mullo_epi32(_mm256_add_epi32(r0, x0), c->vb), c->last, c->mask,
                c->bits, same, &p00, &p01);
    gather_pair(img, _mm256_mullo_epi32(_mm256_add_epi32(r1, x0), c->vb), c->last, c->mask,
                c->bits, same, &p10, &p11);
    const __m256 top = _mm256_add_ps(p00, _mm256_mul_ps(ax, _mm256_sub_ps(p01, p00)));
    const __m256 bot = _mm256_add_ps(p10, _mm256_mul_ps(ax, _mm256_sub_ps(p11, p10)));
    return _mm256_add_ps(top, _mm256_mul_ps(ay, _mm256_sub_ps(bot, top)));
}

/* sample_u8 / sample_u16 (bytes per pixel: 1 or 2) eight lines at a time; the tail by them. */
__attribute__((target("avx2"))) static void sample_narrow_avx2(
    const void *img, int bytes, int w, int h, int cu, int cv, float fu, float fv, float frac,
    int n, const float *u0, const float *v0, const float *su, const float *sv, float *out)
{
    const __m256 vfu = _mm256_set1_ps(fu), vfv = _mm256_set1_ps(fv), vfr = _mm256_set1_ps(frac);
    const __m256 reach = _mm256_set1_ps(MAX_REACH);
    const __m256i ireach = _mm256_set1_epi32((int)MAX_REACH);
    const __m256i vcu = _mm256_set1_epi32(cu), vcv = _mm256_set1_epi32(cv);
    const Narrow c = narrow_frame(w, h, bytes);
    int l = 0;
    for (; l + 8 <= n; l += 8) {
        const __m256 x = _mm256_add_ps(
            vfu, _mm256_add_ps(_mm256_loadu_ps(u0 + l), _mm256_mul_ps(_mm256_loadu_ps(su + l), vfr)));
        const __m256 y = _mm256_add_ps(
            vfv, _mm256_add_ps(_mm256_loadu_ps(v0 + l), _mm256_mul_ps(_mm256_loadu_ps(sv + l), vfr)));
        const __m256i xi = _mm256_sub_epi32(_mm256_cvttps_epi32(_mm256_add_ps(x, reach)), ireach);
        const __m256i yi = _mm256_sub_epi32(_mm256_cvttps_epi32(_mm256_add_ps(y, reach)), ireach);
        const __m256 ax = _mm256_sub_ps(x, _mm256_cvtepi32_ps(xi));
        const __m256 ay = _mm256_sub_ps(y, _mm256_cvtepi32_ps(yi));
        _mm256_storeu_ps(out + l, bilinear_narrow(img, &c, _mm256_add_epi32(xi, vcu),
                                                  _mm256_add_epi32(yi, vcv), ax, ay));
    }
    if (l < n) {
        if (bytes == 1)
            sample_u8((const uint8_t *)img, w, h, cu, cv, fu, fv, frac, n - l, u0 + l, v0 + l,
                      su + l, sv + l, out + l);
        else
            sample_u16((const uint16_t *)img, w, h, cu, cv, fu, fv, frac, n - l, u0 + l, v0 + l,
                       su + l, sv + l, out + l);
    }
}
#endif

/* Set at import: the CPU runs AVX2 (the narrow-pixel samplers above). */
static int have_avx2 = 0;

/* The moments of the forward differences (profile_fit._centroids): centroid, mass and the
 * second central moment. */
SIMD static void moments(int n, Py_ssize_t stride, const float *restrict prof, float pol,
                    const float *restrict lf, const float *restrict sf, float *restrict mean,
                    float *restrict mass, float *restrict m2)
{
    float w0[SAMPLES], w1[SAMPLES], w2[SAMPLES];
    for (int j = 0; j < SAMPLES; j++) {
        w0[j] = (float)W[0][j];
        w1[j] = (float)W[1][j];
        w2[j] = (float)W[2][j];
    }
    for (int l = 0; l < n; l++) {
        float s0 = 0.0f, s1 = 0.0f, s2 = 0.0f;
        for (int j = 0; j < SAMPLES; j++) {
            const float p = prof[j * stride + l];
            s0 += w0[j] * p;
            s1 += w1[j] * p;
            s2 += w2[j] * p;
        }
        const float ms = s0 * pol;
        const float iv = pol / ms;
        const float c1 = s1 * iv;
        const float st = sf[l];
        mass[l] = ms;
        mean[l] = lf[l] + st * c1;
        m2[l] = st * st * (s2 * iv - c1 * c1);
    }
}

/* Ask for the pixels of a fit's box (its ellipse, its windows and a pixel more) before they are
 * needed: a pass goes from fiducial to fiducial across the frame, which no hardware prefetcher
 * follows, and each fiducial's first touch of its rows is otherwise a wait on memory. */
static void prefetch_box(const char *img, Py_ssize_t itemsize, Py_ssize_t w, Py_ssize_t h,
                         const double *e, double cap)
{
    if (!(isfinite(e[0]) && isfinite(e[1]) && isfinite(e[2]))) return;
    const double reach = e[2] + cap + 2.0;
    Py_ssize_t x0 = (Py_ssize_t)(e[0] - reach), x1 = (Py_ssize_t)(e[0] + reach);
    Py_ssize_t y0 = (Py_ssize_t)(e[1] - reach), y1 = (Py_ssize_t)(e[1] + reach);
    x0 = x0 < 0 ? 0 : x0;
    y0 = y0 < 0 ? 0 : y0;
    x1 = x1 > w - 1 ? w - 1 : x1;
    y1 = y1 > h - 1 ? h - 1 : y1;
    if (x1 < x0 || y1 < y0) return;
    for (Py_ssize_t y = y0; y <= y1; y++) {
        const char *row = img + (y * w) * itemsize;
        for (Py_ssize_t x = x0 * itemsize; x <= x1 * itemsize; x += 64)
            __builtin_prefetch(row + x, 0, 1);
        __builtin_prefetch(row + x1 * itemsize, 0, 1);
    }
}

typedef struct {
    Py_buffer src, ellipses, count, cap, polarity;
    Py_buffer valid, jac, kappa, lower, upper, step, mean, mass, m2;
    /* A full edge's terms and sums, optional. */
    Py_buffer blur, z0, v0, good, t, typical, normal, rhs;
} Buffers;

static void release(Buffers *b)
{
    Py_buffer *all[] = {&b->src,   &b->ellipses, &b->count, &b->cap,   &b->polarity, &b->valid,
                        &b->jac,   &b->kappa,    &b->lower, &b->upper, &b->step,     &b->mean,
                        &b->mass,  &b->m2,       &b->blur,  &b->z0,    &b->v0,       &b->good,
                        &b->t,     &b->typical,  &b->normal, &b->rhs};
    for (size_t i = 0; i < sizeof(all) / sizeof(all[0]); i++)
        if (all[i]->obj != NULL) PyBuffer_Release(all[i]);
}

static int sized(Py_buffer *b, Py_ssize_t n, Py_ssize_t itemsize, const char *name)
{
    if (b->len != n * itemsize) {
        PyErr_Format(PyExc_ValueError, "%s: expected %zd items of %zd bytes, got %zd bytes",
                     name, n, itemsize, b->len);
        return 0;
    }
    return 1;
}

/* ---- After the samples: a full edge's usable lines, their edge positions, the sums. ---- */

/* exp(x) for x <= 0 in float32, branch-free (so that loops calling it run in SIMD): 2^n times
 * a degree-6 polynomial of 2^f on (-1, 0], relative error ~2e-7; exp(-87) and below give ~0. */
static inline float exp_neg(float x)
{
    x = x > -87.0f ? x : -87.0f;
    const float t = x * 1.44269504f;
    const int n = (int)t; /* towards zero: f = t - n in (-1, 0] */
    const float f = t - (float)n;
    float p = 1.53533477e-4f;
    p = p * f + 1.33989842e-3f;
    p = p * f + 9.61812911e-3f;
    p = p * f + 5.55041087e-2f;
    p = p * f + 2.40226507e-1f;
    p = p * f + 6.93147182e-1f;
    p = p * f + 1.0f;
    union {
        int i;
        float f;
    } scale;
    scale.i = (n + 127) << 23;
    return p * scale.f;
}

/* erf(t / sqrt(2)) given gauss = exp(-t^2 / 2) (edge_fit.erf_scaled: Abramowitz & Stegun
 * 7.1.26, error < 1.5e-7). */
static inline float erf_scaled(float t, float gauss)
{
    const float z = 1.0f / (1.0f + 0.231641888f * fabsf(t));
    float p = 1.061405429f;
    p = p * z - 1.453152027f;
    p = p * z + 1.421413741f;
    p = p * z - 0.284496736f;
    p = p * z + 0.254829592f;
    const float e = 1.0f - p * z * gauss;
    return copysignf(e, t);
}

/* The first loop of edge_terms over one fit's lines (see there): branch-free, in SIMD. */
SIMD static void edge_lines(Py_ssize_t m, const uint8_t *restrict valid, const float *restrict kap,
                            const float *restrict lower, const float *restrict upper,
                            const float *restrict stepv, const float *restrict mean,
                            const float *restrict mass, float bf, float blur2, float cap_t,
                            float z0f, float v0f, uint8_t *restrict good, float *restrict t,
                            float *restrict height)
{
    const float inv_sqrt_2pi = 0.398942280f;
    for (int l = 0; l < (int)m; l++) {
        const float mu = mean[l], ms = mass[l], lw = lower[l], up = upper[l];
        const float st = stepv[l];
        const float sg = sqrtf(blur2 + st * st * (1.0f / 12.0f));
        /* The edge as the centre of the Gaussian whose window-truncated centroid was measured:
         * the truncated standard normal's mass, mean and variance over the window in spreads
         * (profile_fit._truncated_normal), the fit's symmetric cap's where the window is it. */
        const float al = lw / sg, be = up / sg;
        const float ga = exp_neg(-0.5f * al * al), gb = exp_neg(-0.5f * be * be);
        float zc = 0.5f * (erf_scaled(be, gb) - erf_scaled(al, ga));
        zc = zc > 1e-12f ? zc : 1e-12f;
        const float pa = ga * inv_sqrt_2pi, pb = gb * inv_sqrt_2pi;
        const float mc = (pa - pb) / zc;
        float vc = 1.0f + (al * pa - be * pb) / zc - mc * mc;
        vc = vc > 1e-6f ? vc : 1e-6f;
        const int cut = (lw > -cap_t) | (up < cap_t);
        const float z = cut ? zc : z0f, shift = cut ? mc : 0.0f, gain = cut ? vc : v0f;
        const float pos = (mu - sg * shift) / gain;
        const float least = 2.0f * sg; /* profile_fit._MIN_WINDOW_SPREADS */
        /* NaN centroids fail every comparison. */
        int g = (valid[l] != 0) & (ms > 0.0f) & (pos - lw >= least) & (up - pos >= least);
        g &= kap[l] * bf <= 0.35f; /* profile_fit._MAX_CURVATURE_SPREAD */
        height[l] = ms / (z > 1e-6f ? z : 1e-6f);
        /* A blurred curved edge's centroid lies kappa s^2 / 2 inside it. */
        t[l] = pos + 0.5f * kap[l] * blur2;
        good[l] = (uint8_t)g;
    }
}

/* Python-visible helper: check a buffer's size, release everything on failure. */
#define CHECK(buf, n, size, name) \
    if (ok && !sized(&(buf), (n), (size), (name))) ok = 0

/* A full edge's lines of one fit after their samples (profile_fit._edge_terms, an edge printed
 * all round, at a known blur): the usable lines (good), each one's edge position as the
 * right-hand side t of jac . delta = -t (0 where not usable), and the fit's typical step height,
 * returned (NaN where no line was usable). height: scratch of m floats. */
static double fit_edge_terms(Py_ssize_t m, const uint8_t *valid, const float *kap,
                             const float *lower, const float *upper, const float *stepv,
                             const float *mean, const float *mass, double blur, double cap,
                             double z0, double v0, uint8_t *good, float *t, float *height)
{
    const float bf = (float)blur, blur2 = (float)(blur * blur);
    edge_lines(m, valid, kap, lower, upper, stepv, mean, mass, bf, blur2, (float)cap, (float)z0,
               (float)v0, good, t, height);
    double sum = 0.0;
    Py_ssize_t n = 0;
    for (Py_ssize_t l = 0; l < m; l++) {
        if (good[l]) {
            sum += height[l];
            n++;
        }
    }
    const double typ = n > 0 ? sum / (double)n : NAN;
    const float tf = (float)typ;
    /* The step must be this fiducial's edge: its height near the fit's typical one. */
    for (Py_ssize_t l = 0; l < m; l++) {
        const int g = good[l] && height[l] > 0.5f * tf && height[l] < 1.5f * tf;
        good[l] = (uint8_t)g;
        if (!g) t[l] = 0.0f;
    }
    return typ;
}

/* One fit's least-squares sums over its good lines: normal (5 x 5) = sum jac jac^T and rhs (5)
 * = -sum jac t, in double; jf: its jacobian rows (5 x m). */
static void fit_sums(Py_ssize_t m, const float *jf, const float *tf, const uint8_t *gf,
                     double *normal, double *rhs)
{
    double nn[5][5] = {{0.0}}, rr[5] = {0.0};
    for (Py_ssize_t l = 0; l < m; l++) {
        if (!gf[l]) continue;
        double j[5];
        for (int p = 0; p < 5; p++) j[p] = jf[p * m + l];
        for (int p = 0; p < 5; p++) {
            rr[p] -= j[p] * tf[l];
            for (int q = p; q < 5; q++) nn[p][q] += j[p] * j[q];
        }
    }
    for (int p = 0; p < 5; p++) {
        rhs[p] = rr[p];
        for (int q = 0; q < 5; q++) normal[5 * p + q] = q >= p ? nn[p][q] : nn[q][p];
    }
}

PyDoc_STRVAR(sample_lines_doc,
"sample_lines(src, kind, height, width, ellipses, count, lo, hi, cap, polarity, m,\n"
"             second_moment, valid, jac, kappa, lower, upper, step, mean, mass, m2)\n\n"
"The lines of one profile pass on k ellipses and the moments along them, written into the\n"
"given C-contiguous buffers: src (height, width) of uint8 (kind 0), uint16 (1) or float32 (2)\n"
"pixels; ellipses float64 (k, 5) as (u, v, a,\n"
"b, angle); count int64 (k,); cap, polarity float64 (k,); outputs valid uint8 (k, m), jac\n"
"float32 (k, 5, m), the rest float32 (k, m) (m2 only when second_moment). Padding lines (past a\n"
"fit's count) get valid 0, zero jac, mean NaN, mass 0 and the full window.\n\n"
"Optional, for an edge printed all round at a known blur: blur, z0, v0 float64 (k,) (the blur\n"
"and the symmetric window's truncated-normal mass and variance), then outputs good uint8 (k, m),\n"
"t float32 (k, m), typical float64 (k,), normal float64 (k, 5, 5), rhs float64 (k, 5): each\n"
"fit's usable lines, edge positions as the right-hand side t of jac . delta = -t, typical step\n"
"height (NaN where no line was usable) and least-squares sums (profile_fit._edge_terms, then\n"
"the sums of profile_fit._solve), while the fit's lines are in cache.");

static PyObject *sample_lines(PyObject *self, PyObject *args)
{
    Buffers b;
    memset(&b, 0, sizeof(b));
    Py_ssize_t h, w, m;
    double lo, hi;
    int second, kind;
    if (!PyArg_ParseTuple(args, "y*inny*y*ddy*y*npw*w*w*w*w*w*w*w*w*|y*y*y*w*w*w*w*w*", &b.src,
                          &kind, &h, &w, &b.ellipses, &b.count, &lo, &hi, &b.cap, &b.polarity,
                          &m, &second, &b.valid, &b.jac, &b.kappa, &b.lower, &b.upper, &b.step,
                          &b.mean, &b.mass, &b.m2, &b.blur, &b.z0, &b.v0, &b.good, &b.t,
                          &b.typical, &b.normal, &b.rhs)) {
        release(&b);
        return NULL;
    }
    Py_ssize_t k = b.cap.len / (Py_ssize_t)sizeof(double);
    if (h < 1 || w < 1 || h > INT_MAX / (w > 0 ? w : 1) || m < 0) {
        PyErr_SetString(PyExc_ValueError, "bad image or line count");
        release(&b);
        return NULL;
    }
    if (kind != 0 && kind != 1 && kind != 2) {
        PyErr_Format(PyExc_ValueError, "kind must be 0 (uint8), 1 (uint16) or 2 (float32), got %d",
                     kind);
        release(&b);
        return NULL;
    }
    if (!sized(&b.src, h * w, kind == 0 ? 1 : (kind == 1 ? 2 : 4), "src") || !sized(&b.ellipses, 5 * k, 8, "ellipses") ||
        !sized(&b.count, k, 8, "count") || !sized(&b.cap, k, 8, "cap") ||
        !sized(&b.polarity, k, 8, "polarity") || !sized(&b.valid, k * m, 1, "valid") ||
        !sized(&b.jac, 5 * k * m, 4, "jac") || !sized(&b.kappa, k * m, 4, "kappa") ||
        !sized(&b.lower, k * m, 4, "lower") || !sized(&b.upper, k * m, 4, "upper") ||
        !sized(&b.step, k * m, 4, "step") || !sized(&b.mean, k * m, 4, "mean") ||
        !sized(&b.mass, k * m, 4, "mass") || (second && !sized(&b.m2, k * m, 4, "m2"))) {
        release(&b);
        return NULL;
    }
    const int edges = b.blur.obj != NULL;
    if (edges && (b.rhs.obj == NULL || !sized(&b.blur, k, 8, "blur") || !sized(&b.z0, k, 8, "z0") ||
                  !sized(&b.v0, k, 8, "v0") || !sized(&b.good, k * m, 1, "good") ||
                  !sized(&b.t, k * m, 4, "t") || !sized(&b.typical, k, 8, "typical") ||
                  !sized(&b.normal, 25 * k, 8, "normal") || !sized(&b.rhs, 5 * k, 8, "rhs"))) {
        if (!PyErr_Occurred())
            PyErr_SetString(PyExc_TypeError, "a full edge's terms need all eight buffers");
        release(&b);
        return NULL;
    }
    const double *ell = (const double *)b.ellipses.buf;
    const int64_t *cnt = (const int64_t *)b.count.buf;
    const double *capv = (const double *)b.cap.buf, *pol = (const double *)b.polarity.buf;
    uint8_t *valid = (uint8_t *)b.valid.buf;
    float *jac = (float *)b.jac.buf, *kap = (float *)b.kappa.buf;
    float *lower = (float *)b.lower.buf, *upper = (float *)b.upper.buf;
    float *stepv = (float *)b.step.buf, *mean = (float *)b.mean.buf;
    float *mass = (float *)b.mass.buf, *m2 = second ? (float *)b.m2.buf : NULL;
    /* Per-fit scratch rows: the points' angles, the windows, the samples (sample-major), then
     * the step heights of a full edge's lines. */
    const Py_ssize_t mm = m > 0 ? m : 1;
    float *scratch = (float *)malloc((7 + SAMPLES) * (size_t)mm * sizeof(float));
    if (scratch == NULL) {
        release(&b);
        return PyErr_NoMemory();
    }
    float *cps = scratch, *sps = scratch + mm, *su0 = scratch + 2 * mm, *sv0 = scratch + 3 * mm;
    float *sus = scratch + 4 * mm, *svs = scratch + 5 * mm, *prof = scratch + 6 * mm;
    float *height = prof + SAMPLES * mm;
    const Py_ssize_t itemsize = kind == 0 ? 1 : (kind == 1 ? 2 : 4);
    Py_BEGIN_ALLOW_THREADS
    if (k > 0) prefetch_box((const char *)b.src.buf, itemsize, w, h, ell, capv[0]);
    for (Py_ssize_t f = 0; f < k; f++) {
        const double *e = ell + 5 * f;
        if (f + 1 < k) prefetch_box((const char *)b.src.buf, itemsize, w, h, e + 5, capv[f + 1]);
        const Fit fit = {e[0], e[1], e[2], e[3], e[4], (float)capv[f], (float)pol[f],
                         (float)(1.0 - lo), (float)(hi - 1.0)};
        int n = (int)(cnt[f] < 0 ? 0 : (cnt[f] > m ? m : cnt[f]));
        /* A fit the samples cannot reach safely (not finite, centre off any image, windows past
         * MAX_REACH) gets padding only: no usable line. */
        const double reach = fabs(e[2]) + fabs(capv[f]) + 2.0;
        if (!(isfinite(e[0]) && isfinite(e[1]) && isfinite(e[4]) && fabs(e[0]) < 1e7 &&
              fabs(e[1]) < 1e7 && e[3] > 0.0 && reach < MAX_REACH - 8.0))
            n = 0;
        const Py_ssize_t r = f * m;
        float *j0 = jac + 5 * r;
        angles(&fit, n, cps, sps);
        geometry(&fit, n, cps, sps, kap + r, lower + r, upper + r, stepv + r, j0, j0 + m,
                 j0 + 2 * m, j0 + 3 * m, j0 + 4 * m, su0, sv0, sus, svs);
        const int cu = (int)floor(fit.u), cv = (int)floor(fit.v);
        const float fu = (float)(fit.u - cu), fv = (float)(fit.v - cv);
        for (int j = 0; j < SAMPLES; j++) {
            const float frac = (float)j / (SAMPLES - 1);
            float *out = prof + j * mm;
#ifdef HAVE_AVX2_SAMPLERS
            if (have_avx2 && kind != 2 && w * h * (kind + 1) >= 4 && w * h * (kind + 1) < INT_MAX)
                sample_narrow_avx2(b.src.buf, kind + 1, (int)w, (int)h, cu, cv, fu, fv, frac, n,
                                   su0, sv0, sus, svs, out);
            else
#endif
            if (kind == 0)
                sample_u8((const uint8_t *)b.src.buf, (int)w, (int)h, cu, cv, fu, fv, frac, n,
                          su0, sv0, sus, svs, out);
            else if (kind == 1)
                sample_u16((const uint16_t *)b.src.buf, (int)w, (int)h, cu, cv, fu, fv, frac, n,
                           su0, sv0, sus, svs, out);
            else
                sample_f32((const float *)b.src.buf, (int)w, (int)h, cu, cv, fu, fv, frac, n,
                           su0, sv0, sus, svs, out);
        }
        /* Without the second moment, into scratch (its angle rows, used by then). */
        moments(n, mm, prof, fit.pol, lower + r, stepv + r, mean + r, mass + r,
                m2 != NULL ? m2 + r : cps);
        memset(valid + r, 1, (size_t)n);
        for (Py_ssize_t l = n; l < m; l++) {
            valid[r + l] = 0;
            for (int p = 0; p < 5; p++) j0[p * m + l] = 0.0f;
            kap[r + l] = 0.0f;
            lower[r + l] = -fit.cap;
            upper[r + l] = fit.cap;
            stepv[r + l] = 2.0f * fit.cap / (SAMPLES - 1);
            mean[r + l] = NAN;
            mass[r + l] = 0.0f;
            if (m2 != NULL) m2[r + l] = NAN;
        }
        if (edges) {
            /* The fit's lines are still in cache: its edge terms and sums now. */
            uint8_t *gf = (uint8_t *)b.good.buf + r;
            float *tf = (float *)b.t.buf + r;
            ((double *)b.typical.buf)[f] = fit_edge_terms(
                m, valid + r, kap + r, lower + r, upper + r, stepv + r, mean + r, mass + r,
                ((const double *)b.blur.buf)[f], capv[f], ((const double *)b.z0.buf)[f],
                ((const double *)b.v0.buf)[f], gf, tf, height);
            fit_sums(m, j0, tf, gf, (double *)b.normal.buf + 25 * f, (double *)b.rhs.buf + 5 * f);
        }
    }
    Py_END_ALLOW_THREADS
    free(scratch);
    release(&b);
    Py_RETURN_NONE;
}


PyDoc_STRVAR(normal_sums_doc,
"normal_sums(jac, t, good, m, normal, rhs)\n\n"
"Each fit's least-squares sums over its good lines of jac . delta = -t: normal float64\n"
"(k, 5, 5) = sum jac jac^T and rhs float64 (k, 5) = -sum jac t, from jac float32 (k, 5, m),\n"
"t float32 (k, m) and good uint8 (k, m).");

static PyObject *normal_sums(PyObject *self, PyObject *args)
{
    Py_buffer bj, bt, bg, bn, br;
    memset(&bj, 0, sizeof(bj));
    memset(&bt, 0, sizeof(bt));
    memset(&bg, 0, sizeof(bg));
    memset(&bn, 0, sizeof(bn));
    memset(&br, 0, sizeof(br));
    Py_ssize_t m;
    int ok = PyArg_ParseTuple(args, "y*y*y*nw*w*", &bj, &bt, &bg, &m, &bn, &br);
    Py_ssize_t k = ok && m > 0 ? bt.len / (Py_ssize_t)(4 * m) : 0;
    CHECK(bj, 5 * k * m, 4, "jac");
    CHECK(bt, k * m, 4, "t");
    CHECK(bg, k * m, 1, "good");
    CHECK(bn, 25 * k, 8, "normal");
    CHECK(br, 5 * k, 8, "rhs");
    if (ok) {
        const float *jac = (const float *)bj.buf, *t = (const float *)bt.buf;
        const uint8_t *good = (const uint8_t *)bg.buf;
        double *normal = (double *)bn.buf, *rhs = (double *)br.buf;
        Py_BEGIN_ALLOW_THREADS
        for (Py_ssize_t f = 0; f < k; f++)
            fit_sums(m, jac + 5 * f * m, t + f * m, good + f * m, normal + 25 * f, rhs + 5 * f);
        Py_END_ALLOW_THREADS
    }
    PyBuffer_Release(&bj);
    PyBuffer_Release(&bt);
    PyBuffer_Release(&bg);
    PyBuffer_Release(&bn);
    PyBuffer_Release(&br);
    if (!ok) return NULL;
    Py_RETURN_NONE;
}

/* One fit's first-round residuals t + jac . step over its used lines: returns their RMS (over
 * used - 5, at least 1); the lines beyond limit RMSs leave use and the sums normal (5 x 5) and
 * rhs (5); tt = sum t^2 and used over the lines left. */
static double fit_drop_outliers(Py_ssize_t m, const float *jf, const float *tf, uint8_t *uf,
                                const double *step, double limit, double *normal, double *rhs,
                                double *tt_out, int64_t *used_out)
{
    double ss = 0.0;
    Py_ssize_t n = 0;
    for (Py_ssize_t l = 0; l < m; l++) {
        if (!uf[l]) continue;
        double r = tf[l];
        for (int p = 0; p < 5; p++) r += step[p] * jf[p * m + l];
        ss += r * r;
        n++;
    }
    const double sd = sqrt(ss / (double)(n - 5 > 1 ? n - 5 : 1));
    double tt = 0.0;
    int64_t kept = 0;
    for (Py_ssize_t l = 0; l < m; l++) {
        if (!uf[l]) continue;
        double j[5], r = tf[l];
        for (int p = 0; p < 5; p++) {
            j[p] = jf[p * m + l];
            r += step[p] * j[p];
        }
        if (fabs(r) <= limit * sd) {
            tt += (double)tf[l] * tf[l];
            kept++;
            continue;
        }
        /* A few bad lines come out of the sums (cheaper than summing all again). */
        uf[l] = 0;
        for (int p = 0; p < 5; p++) {
            rhs[p] += j[p] * tf[l];
            for (int q = 0; q < 5; q++) normal[5 * p + q] -= j[p] * j[q];
        }
    }
    *tt_out = tt;
    *used_out = kept;
    return sd;
}

/* Cholesky factor L (lower, row-major 5 x 5) of a 5 x 5 matrix; 0 where it is not positive
 * definite. */
static int cholesky5(const double *a, double *l)
{
    for (int i = 0; i < 25; i++) l[i] = 0.0;
    for (int j = 0; j < 5; j++) {
        double d = a[5 * j + j];
        for (int k = 0; k < j; k++) d -= l[5 * j + k] * l[5 * j + k];
        if (!(d > 0.0) || !isfinite(d)) return 0;
        const double ljj = sqrt(d);
        l[5 * j + j] = ljj;
        for (int i = j + 1; i < 5; i++) {
            double v = a[5 * i + j];
            for (int k = 0; k < j; k++) v -= l[5 * i + k] * l[5 * j + k];
            l[5 * i + j] = v / ljj;
        }
    }
    return 1;
}

/* x = (L L^T)^-1 b. */
static void cholesky5_solve(const double *l, const double *b, double *x)
{
    double y[5];
    for (int i = 0; i < 5; i++) {
        double v = b[i];
        for (int k = 0; k < i; k++) v -= l[5 * i + k] * y[k];
        y[i] = v / l[5 * i + i];
    }
    for (int i = 4; i >= 0; i--) {
        double v = y[i];
        for (int k = i + 1; k < 5; k++) v -= l[5 * k + i] * x[k];
        x[i] = v / l[5 * i + i];
    }
}

/* lhs = normal + scale q, right = rhs - scale q o (a partial edge's prior, where q is given). */
static void with_prior(const double *normal, const double *rhs, const double *q, const double *o,
                       double scale, double *lhs, double *right)
{
    for (int p = 0; p < 5; p++) {
        double qo = 0.0;
        for (int c = 0; c < 5; c++) {
            lhs[5 * p + c] = normal[5 * p + c] + (q != NULL ? scale * q[5 * p + c] : 0.0);
            if (q != NULL) qo += q[5 * p + c] * o[c];
        }
        right[p] = rhs[p] - (q != NULL ? scale * qo : 0.0);
    }
}

/* x = lhs^-1 right by Cholesky; NaN where lhs is not positive definite. Returns 1 if solved. */
static int solve5(const double *lhs, const double *right, double *x, double *l)
{
    if (!cholesky5(lhs, l)) {
        for (int p = 0; p < 5; p++) x[p] = NAN;
        return 0;
    }
    cholesky5_solve(l, right, x);
    return 1;
}

PyDoc_STRVAR(solve_rounds_doc,
"solve_rounds(jac, t, use, m, normal, rhs, q, o, tie_sd, min_lines, limit, delta, inv, sd,\n"
"             used)\n\n"
"Each fit's least squares jac . delta = -t over its used lines (profile_fit._solve), in two\n"
"rounds: a step from the sums normal (k, 5, 5) and rhs (k, 5) (Cholesky), then the lines\n"
"whose residual exceeds limit RMSs out of use (uint8 (k, m)) and the sums (both in place),\n"
"and the step again. q (k, 5, 5) and o (k, 5), or both empty: a partial edge's prior, the step\n"
"then also paying (o + delta)^T q (o + delta) weighed by the lines' sd (tie_sd assumed in the\n"
"first round, the residuals' in the second). A fit with fewer than min_lines used lines, or\n"
"whose system is not positive definite, gets NaN. Outputs: delta float64 (k, 5); inv (k, 5, 5)\n"
"the inverse of the final sums without the prior (the covariance's matrix); sd (k,) the RMS\n"
"residual of the final step; used int64 (k,) (in: the used lines' count; out: after the\n"
"outliers).");

static PyObject *solve_rounds(PyObject *self, PyObject *args)
{
    Py_buffer bj, bt, bu, bn, br, bq, bo, bd, bi, bsd, bused;
    Py_buffer *all[] = {&bj, &bt, &bu, &bn, &br, &bq, &bo, &bd, &bi, &bsd, &bused};
    for (size_t i = 0; i < sizeof(all) / sizeof(all[0]); i++) memset(all[i], 0, sizeof(Py_buffer));
    Py_ssize_t m, min_lines;
    double tie_sd, limit;
    int ok = PyArg_ParseTuple(args, "y*y*w*nw*w*y*y*dndw*w*w*w*", &bj, &bt, &bu, &m, &bn, &br,
                              &bq, &bo, &tie_sd, &min_lines, &limit, &bd, &bi, &bsd, &bused);
    Py_ssize_t k = ok ? bd.len / (Py_ssize_t)(5 * sizeof(double)) : 0;
    CHECK(bj, 5 * k * m, 4, "jac");
    CHECK(bt, k * m, 4, "t");
    CHECK(bu, k * m, 1, "use");
    CHECK(bn, 25 * k, 8, "normal");
    CHECK(br, 5 * k, 8, "rhs");
    const int prior = ok && bq.len != 0;
    if (prior) {
        CHECK(bq, 25 * k, 8, "q");
        CHECK(bo, 5 * k, 8, "o");
    }
    CHECK(bi, 25 * k, 8, "inv");
    CHECK(bsd, k, 8, "sd");
    CHECK(bused, k, 8, "used");
    if (ok) {
        const float *jac = (const float *)bj.buf, *t = (const float *)bt.buf;
        uint8_t *use = (uint8_t *)bu.buf;
        double *normal = (double *)bn.buf, *rhs = (double *)br.buf;
        const double *qv = prior ? (const double *)bq.buf : NULL;
        const double *ov = prior ? (const double *)bo.buf : NULL;
        double *delta = (double *)bd.buf, *inv = (double *)bi.buf, *sdv = (double *)bsd.buf;
        int64_t *usedv = (int64_t *)bused.buf;
        Py_BEGIN_ALLOW_THREADS
        for (Py_ssize_t f = 0; f < k; f++) {
            double *nf = normal + 25 * f, *rf = rhs + 5 * f, *df = delta + 5 * f;
            const double *qf = qv != NULL ? qv + 25 * f : NULL;
            const double *of = ov != NULL ? ov + 5 * f : NULL;
            double lhs[25], right[5], l[25], step[5], tt;
            /* Round one: a step, then the outliers out. */
            for (int p = 0; p < 5; p++) step[p] = 0.0;
            if (usedv[f] >= min_lines) {
                const double s0 = tie_sd > 1e-3 ? tie_sd : 1e-3;
                with_prior(nf, rf, qf, of, s0 * s0, lhs, right);
                if (solve5(lhs, right, step, l) == 0)
                    for (int p = 0; p < 5; p++) step[p] = 0.0;
            }
            const double sd0 = fit_drop_outliers(m, jac + 5 * f * m, t + f * m, use + f * m,
                                                 step, limit, nf, rf, &tt, &usedv[f]);
            /* Round two, on the lines left. */
            for (int p = 0; p < 5; p++) df[p] = NAN;
            for (int p = 0; p < 25; p++) inv[25 * f + p] = NAN;
            if (usedv[f] >= min_lines) {
                const double s1 = sd0 > 1e-3 ? sd0 : 1e-3;
                with_prior(nf, rf, qf, of, s1 * s1, lhs, right);
                solve5(lhs, right, df, l);
                if (cholesky5(nf, l)) {
                    for (int c = 0; c < 5; c++) {
                        double e[5] = {0.0}, x[5];
                        e[c] = 1.0;
                        cholesky5_solve(l, e, x);
                        for (int r = 0; r < 5; r++) inv[25 * f + 5 * r + c] = x[r];
                    }
                }
            }
            /* The residuals' sum of squares from the sums: t.t - 2 delta.r + delta^T N delta
             * over the lines used (r = -J t), no second pass over the lines. */
            double ss = tt;
            for (int p = 0; p < 5; p++) {
                const double sp = isfinite(df[p]) ? df[p] : 0.0;
                ss -= 2.0 * sp * rf[p];
                for (int c = 0; c < 5; c++)
                    ss += sp * nf[5 * p + c] * (isfinite(df[c]) ? df[c] : 0.0);
            }
            const int64_t dof = usedv[f] - 5 > 1 ? usedv[f] - 5 : 1;
            sdv[f] = sqrt((ss > 0.0 ? ss : 0.0) / (double)dof);
        }
        Py_END_ALLOW_THREADS
    }
    for (size_t i = 0; i < sizeof(all) / sizeof(all[0]); i++)
        if (all[i]->obj != NULL) PyBuffer_Release(all[i]);
    if (!ok) return NULL;
    Py_RETURN_NONE;
}

/* Bilinear samples at given points, pixels outside the image reading 0 (cv2.remap with
 * INTER_LINEAR and BORDER_CONSTANT 0, which OpenCV 5 computes in float from the exact
 * positions), integer images' samples rounded to the nearest integer (half to even) as remap
 * returns them in the image's own type. */
/* A point's floor pixel and fractions, far and NaN points first clamped to a pixel or two
 * outside the image (a NaN fails every comparison). */
static inline void point_floor(float x, float y, int w, int h, int *xi, int *yi, float *ax,
                               float *ay)
{
    x = x > -2.0f ? x : -2.0f;
    x = x < (float)w + 1.0f ? x : (float)w + 1.0f;
    y = y > -2.0f ? y : -2.0f;
    y = y < (float)h + 1.0f ? y : (float)h + 1.0f;
    *xi = (int)(x + 4.0f) - 4;
    *yi = (int)(y + 4.0f) - 4;
    *ax = x - (float)*xi;
    *ay = y - (float)*yi;
}

#define POINT_SAMPLER(NAME, TYPE, ROUND) \
SIMD static void NAME(const TYPE *restrict img, int w, int h, Py_ssize_t n, \
                      const float *restrict u, const float *restrict v, float *restrict out) \
{ \
    /* All points as if inside (corners clamped into the image): branch-free, in SIMD. Far \
     * and NaN points are clamped to a pixel or two outside (a NaN fails every comparison). */ \
    for (Py_ssize_t i = 0; i < n; i++) { \
        const float x = u[i], y = v[i]; \
        int xi, yi; \
        float ax, ay; \
        point_floor(x, y, w, h, &xi, &yi, &ax, &ay); \
        int x0 = xi < 0 ? 0 : xi, x1 = xi + 1; \
        x0 = x0 < w - 1 ? x0 : w - 1; \
        x1 = x1 < 0 ? 0 : x1; \
        x1 = x1 < w - 1 ? x1 : w - 1; \
        int y0 = yi < 0 ? 0 : yi, y1 = yi + 1; \
        y0 = y0 < h - 1 ? y0 : h - 1; \
        y1 = y1 < 0 ? 0 : y1; \
        y1 = y1 < h - 1 ? y1 : h - 1; \
        const float p00 = (float)img[y0 * w + x0], p01 = (float)img[y0 * w + x1]; \
        const float p10 = (float)img[y1 * w + x0], p11 = (float)img[y1 * w + x1]; \
        const float top = p00 + ax * (p01 - p00), bot = p10 + ax * (p11 - p10); \
        out[i] = ROUND(top + ay * (bot - top)); \
    } \
    /* Points with a corner outside again, those corners reading 0 (few: a scalar loop). */ \
    for (Py_ssize_t i = 0; i < n; i++) { \
        const float x = u[i], y = v[i]; \
        if (x >= 0.0f && y >= 0.0f && x < (float)(w - 1) && y < (float)(h - 1)) continue; \
        int xi, yi; \
        float ax, ay; \
        point_floor(x, y, w, h, &xi, &yi, &ax, &ay); \
        float p[4]; \
        for (int c = 0; c < 4; c++) { \
            const int px = xi + (c & 1), py = yi + (c >> 1); \
            p[c] = (px >= 0 && px < w && py >= 0 && py < h) ? (float)img[py * w + px] : 0.0f; \
        } \
        const float top = p[0] + ax * (p[1] - p[0]), bot = p[2] + ax * (p[3] - p[2]); \
        out[i] = ROUND(top + ay * (bot - top)); \
    } \
}

#define AS_IS(x) (x)
POINT_SAMPLER(points_u8, uint8_t, rintf)
POINT_SAMPLER(points_u16, uint16_t, rintf)
POINT_SAMPLER(points_f32, float, AS_IS)

#ifdef HAVE_AVX2_SAMPLERS
/* points_u8 / points_u16 (bytes per pixel 1 or 2) eight points at a time (the first loop of
 * POINT_SAMPLER; its second loop, the points near the border, is points_u8's / points_u16's). */
__attribute__((target("avx2"))) static void points_narrow_avx2(const void *img, int bytes, int w,
                                                              int h, Py_ssize_t n,
                                                              const float *u, const float *v,
                                                              float *out)
{
    const __m256 lo = _mm256_set1_ps(-2.0f);
    const __m256 hix = _mm256_set1_ps((float)w + 1.0f), hiy = _mm256_set1_ps((float)h + 1.0f);
    const __m256 four = _mm256_set1_ps(4.0f);
    const __m256i ifour = _mm256_set1_epi32(4);
    const Narrow c = narrow_frame(w, h, bytes);
    Py_ssize_t i = 0;
    for (; i + 8 <= n; i += 8) {
        /* max with the point first: a NaN point becomes the bound. */
        const __m256 x = _mm256_min_ps(_mm256_max_ps(_mm256_loadu_ps(u + i), lo), hix);
        const __m256 y = _mm256_min_ps(_mm256_max_ps(_mm256_loadu_ps(v + i), lo), hiy);
        const __m256i xi = _mm256_sub_epi32(_mm256_cvttps_epi32(_mm256_add_ps(x, four)), ifour);
        const __m256i yi = _mm256_sub_epi32(_mm256_cvttps_epi32(_mm256_add_ps(y, four)), ifour);
        const __m256 ax = _mm256_sub_ps(x, _mm256_cvtepi32_ps(xi));
        const __m256 ay = _mm256_sub_ps(y, _mm256_cvtepi32_ps(yi));
        const __m256 val = bilinear_narrow(img, &c, xi, yi, ax, ay);
        _mm256_storeu_ps(out + i, _mm256_round_ps(val, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC));
    }
    /* The rest, and every point near the border, by the portable loops. */
    if (i < n) {
        if (bytes == 1)
            points_u8((const uint8_t *)img, w, h, n - i, u + i, v + i, out + i);
        else
            points_u16((const uint16_t *)img, w, h, n - i, u + i, v + i, out + i);
    }
    for (Py_ssize_t j = 0; j < i; j++) {
        const float x = u[j], y = v[j];
        if (x >= 0.0f && y >= 0.0f && x < (float)(w - 1) && y < (float)(h - 1)) continue;
        if (bytes == 1)
            points_u8((const uint8_t *)img, w, h, 1, u + j, v + j, out + j);
        else
            points_u16((const uint16_t *)img, w, h, 1, u + j, v + j, out + j);
    }
}
#endif

PyDoc_STRVAR(sample_tracks_doc,
"sample_tracks(src, kind, height, width, centre, axes, angle, drift, weights, out, outside)\n\n"
"The code reader's samples (code_reader._sample_points): for N candidates (centre, axes, drift\n"
"float64 (N, 2), angle float64 (N,)) the K points u = whole + (frac, drift, R diag(a, b)) .\n"
"weights (float32 (4, K), as code_reader._track_maps forms them, in float32 relative to the\n"
"whole pixel nearest the centre), sampled as sample_points does into out float32 (N, K);\n"
"outside uint8 (N, K) marks the points off the image. Each candidate's points are made while\n"
"the previous one's are sampled, and their pixels prefetched.");

/* Points off the image [0, wmax] x [0, hmax] (NaN ones too). */
SIMD static void off_image(Py_ssize_t n, const float *restrict u, const float *restrict v,
                           float wmax, float hmax, uint8_t *restrict out)
{
    for (Py_ssize_t j = 0; j < n; j++) {
        const int in = (u[j] >= 0.0f) & (u[j] <= wmax) & (v[j] >= 0.0f) & (v[j] <= hmax);
        out[j] = (uint8_t)(1 - in);
    }
}

/* One candidate's track points (code_reader._track_maps' arithmetic, in float32). */
SIMD static void track_row(const double *c, const double *ax, double ang, const double *dr,
                           const float *restrict wt, Py_ssize_t kk, float *restrict u,
                           float *restrict v)
{
    const double co = cos(ang), si = sin(ang);
    const double wu = nearbyint(c[0]), wv = nearbyint(c[1]);
    const float cu[4] = {(float)(c[0] - wu), (float)dr[0], (float)(co * ax[0]), (float)(-si * ax[1])};
    const float cv[4] = {(float)(c[1] - wv), (float)dr[1], (float)(si * ax[0]), (float)(co * ax[1])};
    const float fu = (float)wu, fv = (float)wv;
    for (Py_ssize_t j = 0; j < kk; j++) {
        const float w0 = wt[j], w1 = wt[kk + j], w2 = wt[2 * kk + j], w3 = wt[3 * kk + j];
        u[j] = (((cu[0] * w0 + cu[1] * w1) + cu[2] * w2) + cu[3] * w3) + fu;
        v[j] = (((cv[0] * w0 + cv[1] * w1) + cv[2] * w2) + cv[3] * w3) + fv;
    }
}

static PyObject *sample_tracks(PyObject *self, PyObject *args)
{
    Py_buffer bs, bc, ba, bg, bd, bw, bo, bx;
    Py_buffer *all[] = {&bs, &bc, &ba, &bg, &bd, &bw, &bo, &bx};
    for (size_t i = 0; i < sizeof(all) / sizeof(all[0]); i++) memset(all[i], 0, sizeof(Py_buffer));
    int kind = -1;
    Py_ssize_t h = 0, w = 0;
    int ok = PyArg_ParseTuple(args, "y*inny*y*y*y*y*w*w*", &bs, &kind, &h, &w, &bc, &ba, &bg, &bd,
                              &bw, &bo, &bx);
    if (ok && (h < 1 || w < 1 || h > INT_MAX / w || (kind != 0 && kind != 1 && kind != 2))) {
        PyErr_SetString(PyExc_ValueError, "bad image size or pixel kind");
        ok = 0;
    }
    const Py_ssize_t n = ok ? bg.len / 8 : 0;
    const Py_ssize_t kk = ok ? bw.len / 16 : 0;
    CHECK(bs, h * w, kind == 0 ? 1 : (kind == 1 ? 2 : 4), "src");
    CHECK(bc, 2 * n, 8, "centre");
    CHECK(ba, 2 * n, 8, "axes");
    CHECK(bd, 2 * n, 8, "drift");
    CHECK(bw, 4 * kk, 4, "weights");
    CHECK(bo, n * kk, 4, "out");
    CHECK(bx, n * kk, 1, "outside");
    float *rows = NULL;
    if (ok) {
        rows = (float *)malloc(4 * (size_t)(kk > 0 ? kk : 1) * sizeof(float));
        if (rows == NULL) {
            PyErr_NoMemory();
            ok = 0;
        }
    }
    if (ok) {
        const double *centre = (const double *)bc.buf, *axes = (const double *)ba.buf;
        const double *angle = (const double *)bg.buf, *drift = (const double *)bd.buf;
        const float *wt = (const float *)bw.buf;
        float *out = (float *)bo.buf;
        uint8_t *outside = (uint8_t *)bx.buf;
        const int bytes = kind == 0 ? 1 : (kind == 1 ? 2 : 4);
        Py_BEGIN_ALLOW_THREADS
        float *cur = rows, *next = rows + 2 * kk;
        if (n > 0) track_row(centre, axes, angle[0], drift, wt, kk, cur, cur + kk);
        for (Py_ssize_t r = 0; r < n; r++) {
            if (r + 1 < n) {
                /* The next candidate's points now, their pixels asked for. */
                track_row(centre + 2 * (r + 1), axes + 2 * (r + 1), angle[r + 1],
                          drift + 2 * (r + 1), wt, kk, next, next + kk);
                for (Py_ssize_t j = 0; j < kk; j += 4) {
                    const float x = next[j], y = next[kk + j];
                    if (x >= 0.0f && y >= 0.0f && x < (float)w && y < (float)h)
                        __builtin_prefetch((const char *)bs.buf +
                                               ((Py_ssize_t)y * w + (Py_ssize_t)x) * bytes,
                                           0, 1);
                }
            }
            const float *u = cur, *v = cur + kk;
            float *o = out + r * kk;
            uint8_t *x = outside + r * kk;
            off_image(kk, u, v, (float)(w - 1), (float)(h - 1), x);
#ifdef HAVE_AVX2_SAMPLERS
            if (have_avx2 && kind != 2 && w * h * bytes >= 4 && w * h * bytes < INT_MAX)
                points_narrow_avx2(bs.buf, bytes, (int)w, (int)h, kk, u, v, o);
            else
#endif
            if (kind == 0)
                points_u8((const uint8_t *)bs.buf, (int)w, (int)h, kk, u, v, o);
            else if (kind == 1)
                points_u16((const uint16_t *)bs.buf, (int)w, (int)h, kk, u, v, o);
            else
                points_f32((const float *)bs.buf, (int)w, (int)h, kk, u, v, o);
            float *swap = cur;
            cur = next;
            next = swap;
        }
        Py_END_ALLOW_THREADS
    }
    free(rows);
    for (size_t i = 0; i < sizeof(all) / sizeof(all[0]); i++)
        if (all[i]->obj != NULL) PyBuffer_Release(all[i]);
    if (!ok) return NULL;
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"sample_lines", sample_lines, METH_VARARGS, sample_lines_doc},
    {"normal_sums", normal_sums, METH_VARARGS, normal_sums_doc},
    {"solve_rounds", solve_rounds, METH_VARARGS, solve_rounds_doc},
    {"sample_tracks", sample_tracks, METH_VARARGS, sample_tracks_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_profile_kernel",
    "Compiled kernel of fiducial_detector.profile_fit (lines, their moments, edges and sums).", -1, methods,
};

PyMODINIT_FUNC PyInit__profile_kernel(void)
{
    init_weights();
#ifdef HAVE_AVX2_SAMPLERS
    __builtin_cpu_init();
    have_avx2 = __builtin_cpu_supports("avx2");
#endif
    return PyModule_Create(&module);
}
