/* Compiled kernel of fiducial_detector.profile_fit: the lines of one sampling pass and the
 * intensity moments along them (what profile_fit._lines and profile_fit._centroids compute with
 * numpy, in one loop over the lines).
 *
 * Why compiled: numpy spends most of a pass on per-element work over (fits x lines x samples)
 * arrays -- building the sample maps, cv2.remap's per-sample set-up, the moments -- each a trip
 * through memory; here every line is made, sampled and reduced while its few pixels are in cache.
 * Bilinear interpolation is exact here (cv2.remap rounds the sample positions to 1/32 px).
 *
 * Only Python.h: arrays come in through the buffer protocol (C-contiguous, checked by the caller
 * in profile_fit, which owns the shapes and dtypes). No GIL is held while sampling.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <limits.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#define SAMPLES 7

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
        /* floor as the truncation of a positive number: a window lies within 4096 px of its \
         * fit's centre. */ \
        const int xi = (int)(x + 4096.0f) - 4096, yi = (int)(y + 4096.0f) - 4096; \
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

typedef struct {
    Py_buffer src, ellipses, count, cap, polarity;
    Py_buffer valid, jac, kappa, lower, upper, step, mean, mass, m2;
} Buffers;

static void release(Buffers *b)
{
    Py_buffer *all[] = {&b->src, &b->ellipses, &b->count, &b->cap, &b->polarity, &b->valid,
                        &b->jac, &b->kappa, &b->lower, &b->upper, &b->step, &b->mean,
                        &b->mass, &b->m2};
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

PyDoc_STRVAR(sample_lines_doc,
"sample_lines(src, kind, height, width, ellipses, count, lo, hi, cap, polarity, m,\n"
"             second_moment, valid, jac, kappa, lower, upper, step, mean, mass, m2)\n\n"
"The lines of one profile pass on k ellipses and the moments along them, written into the\n"
"given C-contiguous buffers: src (height, width) of uint8 (kind 0), uint16 (1) or float32 (2)\n"
"pixels; ellipses float64 (k, 5) as (u, v, a,\n"
"b, angle); count int64 (k,); cap, polarity float64 (k,); outputs valid uint8 (k, m), jac\n"
"float32 (k, 5, m), the rest float32 (k, m) (m2 only when second_moment). Padding lines (past a\n"
"fit's count) get valid 0, zero jac, mean NaN, mass 0 and the full window.");

static PyObject *sample_lines(PyObject *self, PyObject *args)
{
    Buffers b;
    memset(&b, 0, sizeof(b));
    Py_ssize_t h, w, m;
    double lo, hi;
    int second, kind;
    if (!PyArg_ParseTuple(args, "y*inny*y*ddy*y*npw*w*w*w*w*w*w*w*w*", &b.src, &kind, &h, &w,
                          &b.ellipses, &b.count, &lo, &hi, &b.cap, &b.polarity, &m, &second,
                          &b.valid, &b.jac, &b.kappa, &b.lower, &b.upper, &b.step, &b.mean,
                          &b.mass, &b.m2)) {
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
    const double *ell = (const double *)b.ellipses.buf;
    const int64_t *cnt = (const int64_t *)b.count.buf;
    const double *capv = (const double *)b.cap.buf, *pol = (const double *)b.polarity.buf;
    uint8_t *valid = (uint8_t *)b.valid.buf;
    float *jac = (float *)b.jac.buf, *kap = (float *)b.kappa.buf;
    float *lower = (float *)b.lower.buf, *upper = (float *)b.upper.buf;
    float *stepv = (float *)b.step.buf, *mean = (float *)b.mean.buf;
    float *mass = (float *)b.mass.buf, *m2 = second ? (float *)b.m2.buf : NULL;
    /* Per-fit scratch rows: the points' angles, the windows, then the samples (sample-major). */
    const Py_ssize_t mm = m > 0 ? m : 1;
    float *scratch = (float *)malloc((6 + SAMPLES) * (size_t)mm * sizeof(float));
    if (scratch == NULL) {
        release(&b);
        return PyErr_NoMemory();
    }
    float *cps = scratch, *sps = scratch + mm, *su0 = scratch + 2 * mm, *sv0 = scratch + 3 * mm;
    float *sus = scratch + 4 * mm, *svs = scratch + 5 * mm, *prof = scratch + 6 * mm;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t f = 0; f < k; f++) {
        const double *e = ell + 5 * f;
        const Fit fit = {e[0], e[1], e[2], e[3], e[4], (float)capv[f], (float)pol[f],
                         (float)(1.0 - lo), (float)(hi - 1.0)};
        int n = (int)(cnt[f] < 0 ? 0 : (cnt[f] > m ? m : cnt[f]));
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
    }
    Py_END_ALLOW_THREADS
    free(scratch);
    release(&b);
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"sample_lines", sample_lines, METH_VARARGS, sample_lines_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_profile_kernel",
    "Compiled kernel of fiducial_detector.profile_fit (lines and their moments).", -1, methods,
};

PyMODINIT_FUNC PyInit__profile_kernel(void)
{
    init_weights();
    return PyModule_Create(&module);
}
