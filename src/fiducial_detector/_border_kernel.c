/* Compiled kernel of fiducial_detector.components: the outer boundary of every 8-connected black
 * component of a binary image, by Suzuki & Abe's border following (the algorithm behind
 * cv2.findContours), each reduced to its Green's-theorem moment sums as it is traced.
 *
 *   outer_borders  for every outer border (cv2.findContours' RETR_CCOMP top level, in the same
 *                  raster order): the integer moment sums components._polygon_moments makes
 *                  from its polygon and its length in unit steps, and its chain compressed to
 *                  the ends of straight runs (CHAIN_APPROX_SIMPLE).
 *
 * Why compiled: a 400-fiducial frame has some 3,400 borders, half of them holes; findContours
 * hands each one to Python as its own array (about a microsecond apiece), and the moments were
 * then summed over all of them again in numpy. Here the holes are only followed (their pixels
 * must be marked, or the scan would take a hole's right-hand side for a new component) and each
 * outer border's sums are taken on the way round, exactly, in 64-bit integers.
 *
 * Only Python.h: the binary image comes in through the buffer protocol (C-contiguous uint8,
 * non-zero = black); the results go back as bytes. No GIL is held while working.
 *
 * Reference: S. Suzuki and K. Abe, "Topological structural analysis of digitized binary images
 * by border following", CVGIP 30(1), 1985 (algorithm 1, with the marks it needs and no more).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#if defined(__SSE2__)
#include <emmintrin.h>
#endif

/* Marks in the working copy: 0 white, 1 black not yet on a followed border, and Suzuki's NBD
 * marks, which are only ever compared with 0 and 1 and by sign: POSITIVE ("NBD") and NEGATIVE
 * ("-NBD": the pixel's right-hand neighbour is white and was examined). */
enum { WHITE = 0, BLACK = 1, POSITIVE = 2, NEGATIVE = 3 };

/* Growable output arrays. */
typedef struct {
    char *data;
    size_t used, size;
} Growing;

static int grow(Growing *g, size_t more)
{
    if (g->used + more <= g->size) return 0;
    size_t size = g->size ? g->size : 4096;
    while (size < g->used + more) size *= 2;
    char *data = realloc(g->data, size);
    if (data == NULL) return -1;
    g->data = data;
    g->size = size;
    return 0;
}

/* Chain codes, counter-clockwise as the image is shown (rows down): 0 right, 1 up-right, 2 up,
 * 3 up-left, 4 left, 5 down-left, 6 down, 7 down-right. */
static const int DU[8] = {1, 1, 0, -1, -1, -1, 0, 1};
static const int DV[8] = {0, -1, -1, -1, 0, 1, 1, 1};

typedef struct {
    int64_t s[6]; /* the edge sums of _polygon_moments, unscaled */
    int64_t steps;
} Sums;

/* The moment terms of the edge from (xp, yp) to (x, y) (_polygon_moments' formulas; on a
 * straight run they add up to the run's own terms, so unit steps give the compressed polygon's
 * sums exactly). */
static inline void add_edge(Sums *m, int64_t xp, int64_t yp, int64_t x, int64_t y)
{
    int64_t cross = xp * y - x * yp;
    int64_t xs = xp + x, ys = yp + y;
    m->s[0] += cross;
    m->s[1] += cross * xs;
    m->s[2] += cross * ys;
    m->s[3] += cross * (xs * xs - xp * x);
    m->s[4] += cross * (xs * ys + xp * yp + x * y);
    m->s[5] += cross * (ys * ys - yp * y);
}

/* A chain point (u, v) appended. Returns -1 when out of memory. */
static int push_point(Growing *points, int32_t u, int32_t v)
{
    if (grow(points, 2 * sizeof(int32_t)) < 0) return -1;
    int32_t *p = (int32_t *)(points->data + points->used);
    p[0] = u;
    p[1] = v;
    points->used += 2 * sizeof(int32_t);
    return 0;
}

/* Follows the border that starts at pixel `start` (Suzuki & Abe's step 3), marking it, from the
 * neighbour with code `from` (white: left of an outer border's start, right of a hole's);
 * `delta`: the 16 chain-code offsets in the padded image. With `sums` given, its moment sums and
 * its compressed chain (points relative to the padding, as (u, v) int32 pairs) are taken too.
 * Returns -1 when out of memory. */
static int follow(uint8_t *img, const Py_ssize_t *delta, Py_ssize_t stride, Py_ssize_t start,
                  int from, Sums *sums, Growing *points)
{
    int32_t u = (int32_t)(start % stride) - 1, v = (int32_t)(start / stride) - 1;
    if (sums != NULL) memset(sums, 0, sizeof(*sums));

    /* 3.1: clockwise from `from` (exclusive) round to it, the first black neighbour. */
    int s = from;
    Py_ssize_t i1;
    do {
        s = (s - 1) & 7;
        i1 = start + delta[s];
    } while (img[i1] == WHITE && s != from);
    if (img[i1] == WHITE) { /* a lone pixel */
        img[start] = NEGATIVE;
        if (sums == NULL) return 0;
        sums->steps = 1; /* _polygon_moments counts a lone pixel one step long */
        return push_point(points, u, v);
    }
    Py_ssize_t i3 = start, i4;
    int previous = s ^ 4; /* as cv2: a run is written when the direction changes */
    for (;;) {
        /* 3.3: counter-clockwise from the neighbour we came from, the next black one. */
        int came = s;
        do {
            i4 = i3 + delta[++s];
        } while (img[i4] == WHITE);
        s &= 7;
        /* 3.4: the right-hand neighbour was examined (and white) iff the search passed code 0
         * before finding code s. */
        if ((unsigned)(s - 1) < (unsigned)came)
            img[i3] = NEGATIVE;
        else if (img[i3] == BLACK)
            img[i3] = POSITIVE;
        if (sums != NULL) {
            if (s != previous) {
                if (push_point(points, u, v) < 0) return -1;
                previous = s;
            }
            add_edge(sums, u, v, u + DU[s], v + DV[s]);
            sums->steps++;
            u += DU[s];
            v += DV[s];
        }
        /* 3.5: back at the start, about to go round again. */
        if (i4 == start && i3 == i1) break;
        i3 = i4;
        s = (s + 4) & 7;
    }
    return 0;
}

/* Bit k set where pixel p[k] is white and p[k - 1] black or the reverse, k = 0 .. 15. */
static inline unsigned transitions(const uint8_t *p)
{
#if defined(__SSE2__)
    __m128i zero = _mm_setzero_si128();
    __m128i here = _mm_loadu_si128((const __m128i *)p);
    __m128i left = _mm_loadu_si128((const __m128i *)(p - 1));
    return (unsigned)_mm_movemask_epi8(
        _mm_xor_si128(_mm_cmpeq_epi8(here, zero), _mm_cmpeq_epi8(left, zero)));
#else
    unsigned bits = 0;
    for (int k = 0; k < 16; k++) bits |= (unsigned)((p[k] == 0) != (p[k - 1] == 0)) << k;
    return bits;
#endif
}

static const char outer_borders_doc[] =
    "outer_borders(binary, height, width) -> (sums, points, starts)\n\n"
    "The outer border of every 8-connected non-zero component of a C-contiguous uint8 image, in\n"
    "the raster order of their first pixels (cv2.findContours, RETR_CCOMP's top level):\n"
    "sums, float64 (n, 7): the six unscaled edge sums of components._polygon_moments, then the\n"
    "length in unit steps; points, int32 (m, 2): the chains (u, v), compressed to the ends of\n"
    "straight runs as CHAIN_APPROX_SIMPLE does; starts, int64 (n + 1,): each chain's first\n"
    "point. All as bytes.";

static PyObject *outer_borders(PyObject *self, PyObject *args)
{
    (void)self;
    Py_buffer b;
    Py_ssize_t h, w;
    if (!PyArg_ParseTuple(args, "y*nn", &b, &h, &w)) return NULL;
    if (h < 0 || w < 0 || b.len != h * w || h > INT32_MAX / 2 || w > INT32_MAX / 2) {
        PyBuffer_Release(&b);
        PyErr_Format(PyExc_ValueError, "binary image of %zd bytes is not %zd x %zd", b.len, h, w);
        return NULL;
    }
    /* A copy with a white frame one pixel wide (cv2 sees the same frame round the image), 0/1,
     * and slack after it for the word-wide scan. */
    Py_ssize_t stride = w + 2, total = (h + 2) * stride;
    uint8_t *img = calloc((size_t)total + 16, 1);
    Growing sums = {0}, points = {0}, starts = {0};
    Py_ssize_t delta[16]; /* chain codes 0-7 twice, so that a search may run past code 7 */
    for (int k = 0; k < 16; k++) delta[k] = DU[k & 7] + DV[k & 7] * stride;
    int failed = img == NULL;
    if (!failed) {
        Py_BEGIN_ALLOW_THREADS;
        const uint8_t *src = b.buf;
        for (Py_ssize_t y = 0; y < h; y++) {
            uint8_t *row = img + (y + 1) * stride + 1;
            const uint8_t *in = src + y * w;
            for (Py_ssize_t x = 0; x < w; x++) row[x] = in[x] != 0;
        }
        /* Algorithm 1's raster scan. A border starts only where a pixel's zero-ness differs
         * from its left neighbour's (a white pixel after a black one, or the reverse), and the
         * marks never change zero-ness: those places are found 16 pixels at a time, and only
         * there are the pixels read (as they are then, marks included). */
        for (Py_ssize_t y = 1; y <= h && !failed; y++) {
            uint8_t *row = img + y * stride;
            for (Py_ssize_t x0 = 1; x0 <= w + 1 && !failed; x0 += 16) {
                unsigned changed = transitions(row + x0);
                if (w + 2 - x0 < 16) changed &= (1u << (w + 2 - x0)) - 1; /* the row's end */
                while (changed) {
                    Py_ssize_t x = x0 + __builtin_ctz(changed);
                    changed &= changed - 1;
                    if (row[x - 1] == WHITE) {
                        if (row[x] != BLACK) continue;
                        /* An outer border starts at x. */
                        Sums m;
                        Py_ssize_t at = points.used / (2 * sizeof(int32_t));
                        if (follow(img, delta, stride, y * stride + x, 4, &m, &points) < 0 ||
                            grow(&sums, 7 * sizeof(double)) < 0 ||
                            grow(&starts, sizeof(int64_t)) < 0) {
                            failed = 1;
                            break;
                        }
                        double *out = (double *)(sums.data + sums.used);
                        for (int k = 0; k < 6; k++) out[k] = (double)m.s[k];
                        out[6] = (double)m.steps;
                        sums.used += 7 * sizeof(double);
                        *(int64_t *)(starts.data + starts.used) = (int64_t)at;
                        starts.used += sizeof(int64_t);
                    } else if (row[x - 1] == BLACK || row[x - 1] == POSITIVE) {
                        /* A hole border starts at x - 1: followed for its marks only. */
                        follow(img, delta, stride, y * stride + x - 1, 0, NULL, NULL);
                    }
                }
            }
        }
        if (!failed && grow(&starts, sizeof(int64_t)) == 0) {
            *(int64_t *)(starts.data + starts.used) =
                (int64_t)(points.used / (2 * sizeof(int32_t)));
            starts.used += sizeof(int64_t);
        } else {
            failed = 1;
        }
        Py_END_ALLOW_THREADS;
    }
    free(img);
    PyBuffer_Release(&b);
    PyObject *result = NULL;
    if (failed) {
        PyErr_NoMemory();
    } else {
        result = Py_BuildValue("(y#y#y#)", sums.data ? sums.data : "", (Py_ssize_t)sums.used,
                               points.data ? points.data : "", (Py_ssize_t)points.used,
                               starts.data, (Py_ssize_t)starts.used);
    }
    free(sums.data);
    free(points.data);
    free(starts.data);
    return result;
}

static PyMethodDef methods[] = {
    {"outer_borders", outer_borders, METH_VARARGS, outer_borders_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_border_kernel",
    "Compiled kernel of fiducial_detector.components (Suzuki & Abe's border following).", -1,
    methods,
};

PyMODINIT_FUNC PyInit__border_kernel(void) { return PyModule_Create(&module); }
