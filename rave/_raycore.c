/* The inner loop of RingCaster in C: every (robot, obstacle) pair's run of rays,
 * intersected, each ray keeping its nearest hit; and the sonar's readings made
 * from those hits (noise, dropouts, clipping, quanta).
 *
 * Why C: a sonar scan of a fleet is a few thousand small pairs. As numpy array
 * expressions it took about sixty calls per scan, and at 100 robots the calls'
 * fixed cost, not the arithmetic, bounded the world at about 20x real time. The
 * culling by range (neighbour lists) stays in numpy; this file only does, pair by
 * pair, what rave/raycast.py describes for RingCaster, with the same formulas as
 * its segment_hits and disc_hits.
 *
 * Everything is in the robot's frame, where the ring's rays are constants:
 *   rays (4, M): origin x, origin y, direction x, direction y, sorted by bearing;
 *   below (2 * BINS + 2): how many rays (ring taken twice round) lie below each
 *   bin's lower edge, so a run of bearings becomes a run of rays by two look-ups.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

#define EPS 1e-12
#define TAU 6.283185307179586
/* min and max as one instruction each (fmin and fmax are calls, for NaN rules we
 * do not need: a NaN gap or range fails every comparison made with it anyway) */
#define MIN(a, b) ((a) < (b) ? (a) : (b))
#define MAX(a, b) ((a) > (b) ? (a) : (b))

typedef struct {
    const double *rays;      /* (4, M) */
    const Py_ssize_t *order; /* (M): ray j (by bearing) is the ring's ray order[j] */
    Py_ssize_t m;
    const Py_ssize_t *below; /* (2 * bins + 2) */
    Py_ssize_t bins;
    double radius, max_range;
    double *nearest;         /* (R, M), in the ring's order */
} Ring;

/* Angles into [0, 2 pi). */
static double wrapped(double angle) {
    return angle - TAU * floor(angle / TAU);
}

/* The run of rays (first, count; rays taken modulo M) that can meet an item seen
 * from the robot's centre over bearings low .. low + width, its nearest point
 * `gap` away. count 0: out of reach. */
static void run_of(const Ring *ring, double low, double width, double gap,
                   Py_ssize_t *first, Py_ssize_t *count) {
    if (gap <= ring->radius) {            /* a transducer may be inside it */
        *first = 0;
        *count = ring->m;
        return;
    }
    double widen = asin(MIN(ring->radius / gap, 1.0)) + 1e-9;
    double scale = (double)ring->bins / TAU;
    double start = wrapped(low - widen) * scale;
    double end = MIN(start + (width + 2.0 * widen) * scale, 2.0 * (double)ring->bins);
    if (!(start >= 0.0 && start <= end)) {  /* (not from finite input; stay safe) */
        *first = 0;
        *count = ring->m;
        return;
    }
    Py_ssize_t a = ring->below[(Py_ssize_t)start];
    Py_ssize_t n = ring->below[(Py_ssize_t)end + 1] - a;
    *first = a % ring->m;
    *count = n < ring->m ? n : ring->m;
}

/* Whether an item whose nearest point is `gap` from the centre is out of reach
 * (also for NaN). */
static int beyond(const Ring *ring, double gap) {
    return !(gap <= ring->max_range + ring->radius);
}

/* The next ray of a run, round the ring. */
static Py_ssize_t next_ray(const Ring *ring, Py_ssize_t j) {
    return j + 1 == ring->m ? 0 : j + 1;
}

/* Segment a + u e (0 <= u <= 1), in the robot's frame, against its run of rays. */
static void cast_segment(const Ring *ring, double *row, double ax, double ay,
                         double ex, double ey, double depth) {
    const double *ox = ring->rays, *oy = ox + ring->m, *dx = oy + ring->m, *dy = dx + ring->m;
    double bx = ax + ex, by = ay + ey;
    double length2 = ex * ex + ey * ey, length = sqrt(length2);
    double along = -(ax * ex + ay * ey) / MAX(length2, EPS);
    along = MIN(MAX(along, 0.0), 1.0);
    double gx = ax + along * ex, gy = ay + along * ey;
    double gap = sqrt(gx * gx + gy * gy);
    /* Far side: the centre lies more than the obstacle's depth plus the ring's
     * radius behind the edge; any ray reaching it meets a near side first. */
    if (ey * ax - ex * ay > (depth + ring->radius) * length || beyond(ring, gap))
        return;
    double first_bearing = atan2(ay, ax);
    double turn = wrapped(atan2(by, bx) - first_bearing + M_PI) - M_PI;
    Py_ssize_t j, count;
    run_of(ring, turn >= 0 ? first_bearing : first_bearing + turn, fabs(turn), gap, &j, &count);
    for (Py_ssize_t k = 0; k < count; k++, j = next_ray(ring, j)) {
        /* t = (w x e) / (d x e), u = (w x d) / (d x e), w = a - o */
        double wx = ax - ox[j], wy = ay - oy[j];
        double denom = dx[j] * ey - dy[j] * ex;
        double nu = wx * dy[j] - wy * dx[j];
        if (fabs(denom) < EPS || nu * denom < 0 || fabs(nu) > fabs(denom))
            continue;
        double t = (wx * ey - wy * ex) / denom;
        if (t >= 0 && t <= ring->max_range)
            row[ring->order[j]] = MIN(row[ring->order[j]], t);
    }
}

/* Disc at c (robot's frame) of radius r against its run of rays (a ray from inside
 * it meets it at once). */
static void cast_disc(const Ring *ring, double *row, double cx, double cy, double r) {
    const double *ox = ring->rays, *oy = ox + ring->m, *dx = oy + ring->m, *dy = dx + ring->m;
    double distance = sqrt(cx * cx + cy * cy);
    if (beyond(ring, distance - r))
        return;
    double half = distance > 0 ? asin(MIN(MAX(r / distance, 0.0), 1.0)) : M_PI / 2;
    Py_ssize_t j, count;
    run_of(ring, atan2(cy, cx) - half, 2.0 * half, distance - r, &j, &count);
    for (Py_ssize_t k = 0; k < count; k++, j = next_ray(ring, j)) {
        double mx = ox[j] - cx, my = oy[j] - cy;
        double b = mx * dx[j] + my * dy[j];
        double c = mx * mx + my * my - r * r;
        double disc = b * b - c;
        if (c <= 0) {                        /* from inside the disc: met at once */
            row[ring->order[j]] = MIN(row[ring->order[j]], 0.0);
            continue;
        }
        if (disc < 0)
            continue;
        double t = -b - sqrt(disc);
        if (t >= 0 && t <= ring->max_range)
            row[ring->order[j]] = MIN(row[ring->order[j]], t);
    }
}

/* A C-contiguous buffer of doubles ("d") or of Py_ssize_t ("n"), `count` items
 * (-1: any number) in rows of `row` items, or an error naming the argument. */
static int get(PyObject *object, Py_buffer *view, char kind, Py_ssize_t count,
               Py_ssize_t row, const char *name) {
    if (PyObject_GetBuffer(object, view, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0)
        return -1;
    const char *format = view->format;
    int ok = kind == 'd' ? strcmp(format, "d") == 0
                         : view->itemsize == sizeof(Py_ssize_t)
                           && (strcmp(format, "n") == 0 || strcmp(format, "l") == 0
                               || strcmp(format, "q") == 0);
    Py_ssize_t items = ok ? view->len / view->itemsize : 0;
    if (!ok || items % row || (count >= 0 && items != count)) {
        PyErr_Format(PyExc_ValueError, "cast_pairs: %s must be contiguous %s in rows of %zd"
                     " (%zd items wanted, -1: any)", name,
                     kind == 'd' ? "float64" : "intp", row, count);
        PyBuffer_Release(view);
        return -1;
    }
    return 0;
}

enum { POSES, RAYS, ORDER, BELOW, SEGMENTS, DEPTHS, SEG_ROBOT, SEG_ITEM, DISCS,
       DISC_ROBOT, DISC_ITEM, NEAREST, NBUF };

/* cast_pairs(poses, rays, order, below, segments, depths, seg_robot, seg_item, discs,
 *            disc_robot, disc_item, nearest, radius, max_range)
 * Lowers nearest (R, M) where a paired item's run of rays meets it sooner. */
static PyObject *cast_pairs(PyObject *Py_UNUSED(module), PyObject *const *args,
                            Py_ssize_t nargs) {
    static const char *names[NBUF] = {"poses", "rays", "order", "below", "segments",
                                      "depths", "seg_robot", "seg_item", "discs",
                                      "disc_robot", "disc_item", "nearest"};
    if (nargs != NBUF + 2) {
        PyErr_SetString(PyExc_TypeError, "cast_pairs takes 14 arguments");
        return NULL;
    }
    double radius = PyFloat_AsDouble(args[NBUF]), max_range = PyFloat_AsDouble(args[NBUF + 1]);
    if (PyErr_Occurred())
        return NULL;
    Py_buffer b[NBUF] = {{0}};
    PyObject *result = NULL;
    Py_ssize_t robots, m, bins, segments, seg_pairs, discs, disc_pairs;
    if (get(args[POSES], &b[POSES], 'd', -1, 3, names[POSES]) < 0
            || get(args[RAYS], &b[RAYS], 'd', -1, 4, names[RAYS]) < 0
            || get(args[BELOW], &b[BELOW], 'n', -1, 2, names[BELOW]) < 0
            || get(args[SEGMENTS], &b[SEGMENTS], 'd', -1, 4, names[SEGMENTS]) < 0
            || get(args[DISCS], &b[DISCS], 'd', -1, 3, names[DISCS]) < 0
            || get(args[SEG_ROBOT], &b[SEG_ROBOT], 'n', -1, 1, names[SEG_ROBOT]) < 0
            || get(args[DISC_ROBOT], &b[DISC_ROBOT], 'n', -1, 1, names[DISC_ROBOT]) < 0)
        goto done;
    robots = b[POSES].len / (3 * (Py_ssize_t)sizeof(double));
    m = b[RAYS].len / (4 * (Py_ssize_t)sizeof(double));
    bins = (b[BELOW].len / (Py_ssize_t)sizeof(Py_ssize_t) - 2) / 2;
    segments = b[SEGMENTS].len / (4 * (Py_ssize_t)sizeof(double));
    discs = b[DISCS].len / (3 * (Py_ssize_t)sizeof(double));
    seg_pairs = b[SEG_ROBOT].len / (Py_ssize_t)sizeof(Py_ssize_t);
    disc_pairs = b[DISC_ROBOT].len / (Py_ssize_t)sizeof(Py_ssize_t);
    if (get(args[ORDER], &b[ORDER], 'n', m, 1, names[ORDER]) < 0
            || get(args[DEPTHS], &b[DEPTHS], 'd', segments, 1, names[DEPTHS]) < 0
            || get(args[SEG_ITEM], &b[SEG_ITEM], 'n', seg_pairs, 1, names[SEG_ITEM]) < 0
            || get(args[DISC_ITEM], &b[DISC_ITEM], 'n', disc_pairs, 1, names[DISC_ITEM]) < 0
            || get(args[NEAREST], &b[NEAREST], 'd', robots * m, 1, names[NEAREST]) < 0)
        goto done;
    if (b[NEAREST].readonly) {
        PyErr_SetString(PyExc_ValueError, "cast_pairs: nearest must be writable");
        goto done;
    }
    if (bins < 1 || m < 1) {
        PyErr_SetString(PyExc_ValueError, "cast_pairs: a ring needs rays and bins");
        goto done;
    }
    const Py_ssize_t *order = b[ORDER].buf, *below = b[BELOW].buf;
    for (Py_ssize_t j = 0; j < m; j++)
        if (order[j] < 0 || order[j] >= m) {
            PyErr_SetString(PyExc_ValueError, "cast_pairs: order is not a ray permutation");
            goto done;
        }
    for (Py_ssize_t i = 0; i < 2 * bins + 2; i++)
        if (below[i] < 0 || below[i] > 2 * m || (i && below[i] < below[i - 1])) {
            PyErr_SetString(PyExc_ValueError, "cast_pairs: below is not a ray count table");
            goto done;
        }
    const Py_ssize_t *sr = b[SEG_ROBOT].buf, *si = b[SEG_ITEM].buf;
    const Py_ssize_t *dr = b[DISC_ROBOT].buf, *di = b[DISC_ITEM].buf;
    for (Py_ssize_t p = 0; p < seg_pairs; p++)
        if (sr[p] < 0 || sr[p] >= robots || si[p] < 0 || si[p] >= segments) {
            PyErr_SetString(PyExc_IndexError, "cast_pairs: a segment pair is out of range");
            goto done;
        }
    for (Py_ssize_t p = 0; p < disc_pairs; p++)
        if (dr[p] < 0 || dr[p] >= robots || di[p] < 0 || di[p] >= discs) {
            PyErr_SetString(PyExc_IndexError, "cast_pairs: a disc pair is out of range");
            goto done;
        }

    /* each robot's heading as cos, sin: (R, 2) */
    double *turns = PyMem_Malloc((size_t)(2 * robots + 1) * sizeof(double));
    if (turns == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    Ring ring = {b[RAYS].buf, order, m, below, bins, radius, max_range, b[NEAREST].buf};
    const double *pose = b[POSES].buf, *seg = b[SEGMENTS].buf, *depth = b[DEPTHS].buf;
    const double *disc = b[DISCS].buf;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t r = 0; r < robots; r++) {
        turns[2 * r] = cos(pose[3 * r + 2]);
        turns[2 * r + 1] = sin(pose[3 * r + 2]);
    }
    for (Py_ssize_t p = 0; p < seg_pairs; p++) {
        const double *at = pose + 3 * sr[p], *s = seg + 4 * si[p];
        double c = turns[2 * sr[p]], sn = turns[2 * sr[p] + 1];
        double x0 = s[0] - at[0], y0 = s[1] - at[1], x1 = s[2] - at[0], y1 = s[3] - at[1];
        double ax = c * x0 + sn * y0, ay = c * y0 - sn * x0;
        double bx = c * x1 + sn * y1, by = c * y1 - sn * x1;
        cast_segment(&ring, ring.nearest + m * sr[p], ax, ay, bx - ax, by - ay, depth[si[p]]);
    }
    for (Py_ssize_t p = 0; p < disc_pairs; p++) {
        const double *at = pose + 3 * dr[p], *d = disc + 3 * di[p];
        double c = turns[2 * dr[p]], sn = turns[2 * dr[p] + 1];
        double x = d[0] - at[0], y = d[1] - at[1];
        cast_disc(&ring, ring.nearest + m * dr[p], c * x + sn * y, c * y - sn * x, d[2]);
    }
    Py_END_ALLOW_THREADS
    PyMem_Free(turns);
    result = Py_NewRef(Py_None);
done:
    for (int i = 0; i < NBUF; i++)
        if (b[i].obj != NULL)
            PyBuffer_Release(&b[i]);
    return result;
}

/* readings(ranges, rays, normal, dropped, readings, sigma0, sigma_per_m, quantum,
 *          min_range, max_range)
 * Fills readings with sonar readings, each from the nearest of `rays` consecutive
 * ray ranges (inf: no echo), as sonar.readings describes: noise (standard normal
 * draws scaled by sigma0 + sigma_per_m * range), dropouts (dropped: a byte per
 * reading, nonzero where the echo is lost; or None), clipping, whole quanta
 * (rounded half to even, as numpy). One pass instead of a dozen numpy calls, the
 * slowest a reduction over axes of five. */
static PyObject *readings(PyObject *Py_UNUSED(module), PyObject *const *args,
                          Py_ssize_t nargs) {
    if (nargs != 10) {
        PyErr_SetString(PyExc_TypeError, "readings takes 10 arguments");
        return NULL;
    }
    Py_ssize_t rays = PyLong_AsSsize_t(args[1]);
    double sigma0 = PyFloat_AsDouble(args[5]), sigma_per_m = PyFloat_AsDouble(args[6]);
    double quantum = PyFloat_AsDouble(args[7]), low = PyFloat_AsDouble(args[8]);
    double high = PyFloat_AsDouble(args[9]);
    if (PyErr_Occurred())
        return NULL;
    if (!(quantum > 0) || rays < 1) {
        PyErr_SetString(PyExc_ValueError, "readings: quantum and rays must be positive");
        return NULL;
    }
    Py_buffer ranges = {0}, normal = {0}, dropped = {0}, out = {0};
    PyObject *result = NULL;
    if (get(args[0], &ranges, 'd', -1, rays, "ranges") < 0)
        return NULL;
    Py_ssize_t n = ranges.len / (Py_ssize_t)sizeof(double) / rays;
    if (get(args[2], &normal, 'd', n, 1, "normal") < 0
            || get(args[4], &out, 'd', n, 1, "readings") < 0)
        goto done;
    if (args[3] != Py_None) {
        if (PyObject_GetBuffer(args[3], &dropped, PyBUF_C_CONTIGUOUS) < 0)
            goto done;
        if (dropped.len != n) {
            PyErr_SetString(PyExc_ValueError, "readings: dropped must hold a byte per reading");
            goto done;
        }
    }
    if (out.readonly) {
        PyErr_SetString(PyExc_ValueError, "readings: readings must be writable");
        goto done;
    }
    const double *range = ranges.buf, *draw = normal.buf;
    const unsigned char *lost = dropped.buf;
    double *reading = out.buf;
    for (Py_ssize_t i = 0; i < n; i++) {
        double r = range[i * rays];
        for (Py_ssize_t k = 1; k < rays; k++)
            r = MIN(r, range[i * rays + k]);
        if (r < INFINITY && !(lost && lost[i])) {
            r += draw[i] * (sigma0 + sigma_per_m * r);
            r = MIN(MAX(r, low), high);
        } else {
            r = high;
        }
        reading[i] = nearbyint(r / quantum) * quantum;
    }
    result = Py_NewRef(Py_None);
done:
    PyBuffer_Release(&ranges);
    if (normal.obj != NULL)
        PyBuffer_Release(&normal);
    if (dropped.obj != NULL)
        PyBuffer_Release(&dropped);
    if (out.obj != NULL)
        PyBuffer_Release(&out);
    return result;
}

static PyMethodDef methods[] = {
    {"cast_pairs", (PyCFunction)(void (*)(void))cast_pairs, METH_FASTCALL,
     "lower each ray's nearest hit by the paired segments and discs' runs of rays"},
    {"readings", (PyCFunction)(void (*)(void))readings, METH_FASTCALL,
     "sonar readings from the rays' ranges and noise draws"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_raycore",
                                    "RingCaster's pair loop and the sonar's readings in C.",
                                    -1, methods};

PyMODINIT_FUNC PyInit__raycore(void) {
    return PyModule_Create(&module);
}
