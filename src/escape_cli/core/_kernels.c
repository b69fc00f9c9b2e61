/* escape_cli.core._kernels: the loops numpy cannot vectorise, in compiled code.
 *
 * fps: farthest point sampling (core/sampling.py). knn: k nearest neighbours in a
 * uniform grid (core/neighbours.py). Both release the interpreter lock.
 *
 * Compile without floating-point contraction (-ffp-contract=off): a fused multiply-add
 * would change the distances' last bits and with them near-tie decisions.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

/* ------------------------------------------------------------------ fps
 *
 * The same choices as `farthest_point_sampling_naive`: every point keeps its squared
 * distance to the chosen set, computed with the naive loop's operations
 * ((dx*dx + dy*dy) + dz*dz); a minimum is exact in any order and sqrt is correctly
 * rounded (so monotone), hence sqrt(min d2) is the naive loop's float. The farthest
 * point is chosen, near-ties within TIE_RTOL of it broken by the larger distance to the
 * centroid, then by the lower index.
 *
 * The points arrive in blocks of BLOCK consecutive slots (the caller orders them along a
 * space-filling curve and pads the last block). A new choice updates only the blocks it
 * can reach: a block whose bounding sphere lies farther from it than the block's largest
 * distance cannot change. Blocks decide which work is skipped, never a result.
 */

#define BLOCK 16
#define TIE_RTOL 1e-9

typedef struct {
    const double *xyz;     /* (S, 3) coordinates by slot */
    const int64_t *order;  /* (S,) slot -> point index */
    const double *radius;  /* (N,) distance to the centroid, by point index */
    double *d2;            /* (S,) squared distance to the chosen set; pads -1 */
    double *b_max;         /* (B,) largest d2 of each block */
    double *b_reach;       /* (B,) sqrt(max(b_max, 0)) */
    double *b_centre;      /* (B, 3) */
    double *b_radius;      /* (B,) */
    Py_ssize_t blocks;
    double slack;
} State;

static void block_sphere(State *s, Py_ssize_t b) {
    const double *p = s->xyz + 3 * b * BLOCK;
    double cx = 0.0, cy = 0.0, cz = 0.0, r2 = 0.0;
    for (int k = 0; k < BLOCK; k++) {
        cx += p[3 * k];
        cy += p[3 * k + 1];
        cz += p[3 * k + 2];
    }
    cx /= BLOCK;
    cy /= BLOCK;
    cz /= BLOCK;
    for (int k = 0; k < BLOCK; k++) {
        double dx = p[3 * k] - cx, dy = p[3 * k + 1] - cy, dz = p[3 * k + 2] - cz;
        double d = (dx * dx + dy * dy) + dz * dz;
        if (d > r2) r2 = d;
    }
    s->b_centre[3 * b] = cx;
    s->b_centre[3 * b + 1] = cy;
    s->b_centre[3 * b + 2] = cz;
    s->b_radius[b] = sqrt(r2) * (1.0 + 1e-12);
}

/* Lower the distances of block b to the point q; refresh its maximum. */
static void update_block(State *s, Py_ssize_t b, const double *q) {
    const double *p = s->xyz + 3 * b * BLOCK;
    double *d2 = s->d2 + b * BLOCK;
    double top = -1.0;
    for (int k = 0; k < BLOCK; k++) {
        double dx = p[3 * k] - q[0], dy = p[3 * k + 1] - q[1], dz = p[3 * k + 2] - q[2];
        double d = (dx * dx + dy * dy) + dz * dz;
        if (d < d2[k]) d2[k] = d;
        if (d2[k] > top) top = d2[k];
    }
    s->b_max[b] = top;
    s->b_reach[b] = top > 0.0 ? sqrt(top) : 0.0;
}

static void update(State *s, const double *q) {
    for (Py_ssize_t b = 0; b < s->blocks; b++) {
        const double *c = s->b_centre + 3 * b;
        double dx = c[0] - q[0], dy = c[1] - q[1], dz = c[2] - q[2];
        double gap = sqrt((dx * dx + dy * dy) + dz * dz) - s->b_radius[b];
        if (gap >= s->b_reach[b] + s->slack) continue; /* no point of b can come closer */
        update_block(s, b, q);
    }
}

/* The next choice: a slot, or -1 when every remaining distance is 0. */
static Py_ssize_t choose(const State *s) {
    double top = -1.0;
    for (Py_ssize_t b = 0; b < s->blocks; b++)
        if (s->b_max[b] > top) top = s->b_max[b];
    double best = top > 0.0 ? sqrt(top) : 0.0;
    if (best <= 0.0) return -1;
    double keep = best * (1.0 - TIE_RTOL);
    Py_ssize_t pick = -1;
    int64_t pick_index = 0;
    double pick_radius = 0.0;
    for (Py_ssize_t b = 0; b < s->blocks; b++) {
        if (s->b_reach[b] < keep) continue;
        for (Py_ssize_t j = b * BLOCK; j < (b + 1) * BLOCK; j++) {
            if (s->d2[j] < 0.0 || sqrt(s->d2[j]) < keep) continue;
            int64_t index = s->order[j];
            double r = s->radius[index];
            if (pick < 0 || r > pick_radius || (r == pick_radius && index < pick_index)) {
                pick = j;
                pick_index = index;
                pick_radius = r;
            }
        }
    }
    return pick;
}

static int check_buffer(Py_buffer *buf, const char *name, Py_ssize_t items, Py_ssize_t itemsize) {
    if (buf->len != items * itemsize) {
        PyErr_Format(PyExc_ValueError, "%s: expected %zd bytes, got %zd", name, items * itemsize, buf->len);
        return -1;
    }
    return 0;
}

PyDoc_STRVAR(fps_doc,
    "fps(xyz, order, radius, first_slot, out) -> number of choices made\n\n"
    "xyz: (S, 3) float64 by slot, S a multiple of 16, the last S - n slots pads; order: (S,)\n"
    "int64 slot -> point index; radius: (n,) float64 distance to the centroid by point index;\n"
    "first_slot: slot of the first choice; out: (count,) int64 filled with point indices.\n"
    "Fewer than count choices are made when the distinct points run out.");

static PyObject *fps(PyObject *self, PyObject *args) {
    Py_buffer xyz, order, radius, out;
    Py_ssize_t n, first;
    if (!PyArg_ParseTuple(args, "y*y*y*nnw*", &xyz, &order, &radius, &n, &first, &out)) return NULL;
    PyObject *result = NULL;
    State s = {0};
    Py_ssize_t slots = xyz.len / (3 * (Py_ssize_t)sizeof(double));
    Py_ssize_t count = out.len / (Py_ssize_t)sizeof(int64_t);
    if (slots % BLOCK || n < 1 || n > slots || first < 0 || first >= n ||
        check_buffer(&xyz, "xyz", 3 * slots, sizeof(double)) ||
        check_buffer(&order, "order", slots, sizeof(int64_t)) ||
        check_buffer(&radius, "radius", n, sizeof(double)) ||
        check_buffer(&out, "out", count, sizeof(int64_t))) {
        if (!PyErr_Occurred()) PyErr_SetString(PyExc_ValueError, "fps: inconsistent sizes");
        goto done;
    }
    s.xyz = xyz.buf;
    s.order = order.buf;
    s.radius = radius.buf;
    s.blocks = slots / BLOCK;
    s.d2 = malloc(sizeof(double) * slots);
    s.b_max = malloc(sizeof(double) * s.blocks);
    s.b_reach = malloc(sizeof(double) * s.blocks);
    s.b_centre = malloc(sizeof(double) * 3 * s.blocks);
    s.b_radius = malloc(sizeof(double) * s.blocks);
    if (!s.d2 || !s.b_max || !s.b_reach || !s.b_centre || !s.b_radius) {
        PyErr_NoMemory();
        goto done;
    }
    int64_t *chosen = out.buf;
    Py_ssize_t made = 0;
    Py_BEGIN_ALLOW_THREADS
    double extent = 0.0, widest = 0.0;
    for (Py_ssize_t j = 0; j < 3 * slots; j++)
        if (fabs(s.xyz[j]) > extent) extent = fabs(s.xyz[j]);
    for (Py_ssize_t b = 0; b < s.blocks; b++) {
        block_sphere(&s, b);
        if (s.b_radius[b] > widest) widest = s.b_radius[b];
    }
    s.slack = 1e-9 * (extent + widest + 1e-300);
    for (Py_ssize_t j = 0; j < slots; j++) s.d2[j] = j < n ? INFINITY : -1.0;
    Py_ssize_t slot = first;
    for (Py_ssize_t b = 0; b < s.blocks; b++) update_block(&s, b, s.xyz + 3 * slot);
    while (made < count) {
        chosen[made++] = s.order[slot];
        if (made == count) break;
        slot = choose(&s);
        if (slot < 0) break;
        update(&s, s.xyz + 3 * slot);
    }
    Py_END_ALLOW_THREADS
    result = PyLong_FromSsize_t(made);
done:
    free(s.d2);
    free(s.b_max);
    free(s.b_reach);
    free(s.b_centre);
    free(s.b_radius);
    PyBuffer_Release(&xyz);
    PyBuffer_Release(&order);
    PyBuffer_Release(&radius);
    PyBuffer_Release(&out);
    return result;
}

/* ------------------------------------------------------------------ knn
 *
 * The k nearest reference points of each query, ordered by (distance, index): exact,
 * with distances sqrt((dx*dx + dy*dy) + dz*dz) as scipy's cKDTree computes them. The
 * reference points are sorted into cubic cells (a counting sort); a query visits rings
 * of cells around its own, nearest rings first, until its k-th distance is below the
 * distance to every cell not yet visited.
 */

typedef struct {
    const double *ref;      /* (M, 3) */
    Py_ssize_t m;
    double origin[3], cell;
    Py_ssize_t dims[3];
    Py_ssize_t *start;      /* (cells + 1,) first sorted position of each cell */
    Py_ssize_t *sorted;     /* (M,) reference rows by cell */
} Grid;

static Py_ssize_t cell_coord(double v, double origin, double cell) {
    double c = floor((v - origin) / cell);
    if (c < -1e9) c = -1e9; /* far queries: a bounded ring count, still a lower bound */
    if (c > 1e9) c = 1e9;
    return (Py_ssize_t)c;
}

static int grid_build(Grid *g, const double *ref, Py_ssize_t m) {
    double lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
    for (Py_ssize_t i = 0; i < m; i++)
        for (int a = 0; a < 3; a++) {
            if (ref[3 * i + a] < lo[a]) lo[a] = ref[3 * i + a];
            if (ref[3 * i + a] > hi[a]) hi[a] = ref[3 * i + a];
        }
    double extent = 0.0;
    for (int a = 0; a < 3; a++)
        if (hi[a] - lo[a] > extent) extent = hi[a] - lo[a];
    /* cells of side extent / cbrt(m / 2), at most 128 a side: a few points a cell on a surface */
    double per_side = cbrt((double)m / 2.0);
    if (per_side > 128.0) per_side = 128.0;
    if (per_side < 1.0) per_side = 1.0;
    g->cell = extent > 0.0 ? extent / per_side : 1.0;
    Py_ssize_t cells = 1;
    for (int a = 0; a < 3; a++) {
        g->origin[a] = lo[a];
        Py_ssize_t d = (Py_ssize_t)floor((hi[a] - lo[a]) / g->cell) + 1;
        g->dims[a] = d < 1 ? 1 : d;
        cells *= g->dims[a];
    }
    g->ref = ref;
    g->m = m;
    g->start = calloc(cells + 1, sizeof(Py_ssize_t));
    g->sorted = malloc(sizeof(Py_ssize_t) * (m > 0 ? m : 1));
    Py_ssize_t *which = malloc(sizeof(Py_ssize_t) * (m > 0 ? m : 1));
    if (!g->start || !g->sorted || !which) {
        free(which);
        return -1;
    }
    for (Py_ssize_t i = 0; i < m; i++) {
        Py_ssize_t c[3];
        for (int a = 0; a < 3; a++) {
            c[a] = cell_coord(ref[3 * i + a], g->origin[a], g->cell);
            if (c[a] >= g->dims[a]) c[a] = g->dims[a] - 1;
            if (c[a] < 0) c[a] = 0;
        }
        which[i] = (c[2] * g->dims[1] + c[1]) * g->dims[0] + c[0];
        g->start[which[i] + 1]++;
    }
    for (Py_ssize_t c = 0; c < cells; c++) g->start[c + 1] += g->start[c];
    Py_ssize_t *fill = malloc(sizeof(Py_ssize_t) * (cells > 0 ? cells : 1));
    if (!fill) {
        free(which);
        return -1;
    }
    for (Py_ssize_t c = 0; c < cells; c++) fill[c] = g->start[c];
    for (Py_ssize_t i = 0; i < m; i++) g->sorted[fill[which[i]]++] = i; /* ascending rows within a cell */
    free(fill);
    free(which);
    return 0;
}

/* Offer reference row i at squared distance d to the sorted best list of size `have` (<= k). */
static Py_ssize_t offer(double *bd, int64_t *bi, Py_ssize_t have, Py_ssize_t k, double d, int64_t i) {
    if (have == k && (d > bd[k - 1] || (d == bd[k - 1] && i > bi[k - 1]))) return have;
    Py_ssize_t j = have < k ? have++ : k - 1;
    while (j > 0 && (bd[j - 1] > d || (bd[j - 1] == d && bi[j - 1] > i))) {
        bd[j] = bd[j - 1];
        bi[j] = bi[j - 1];
        j--;
    }
    bd[j] = d;
    bi[j] = i;
    return have;
}

/* Squared distance from q to the box of cell (cx, cy, cz), a lower bound for its points. */
static double cell_gap2(const Grid *g, Py_ssize_t cx, Py_ssize_t cy, Py_ssize_t cz, const double *q) {
    Py_ssize_t c[3] = {cx, cy, cz};
    double sum = 0.0;
    for (int a = 0; a < 3; a++) {
        double lo = g->origin[a] + (double)c[a] * g->cell, hi = lo + g->cell, d = 0.0;
        if (q[a] < lo) d = lo - q[a];
        else if (q[a] > hi) d = q[a] - hi;
        sum += d * d;
    }
    return sum * (1.0 - 1e-12);
}

static void scan_cell(const Grid *g, Py_ssize_t cx, Py_ssize_t cy, Py_ssize_t cz, const double *q,
                      double *bd, int64_t *bi, Py_ssize_t *have, Py_ssize_t k, double limit2) {
    Py_ssize_t c = (cz * g->dims[1] + cy) * g->dims[0] + cx;
    if (g->start[c] == g->start[c + 1]) return;
    double worst = *have == k ? bd[k - 1] : limit2;
    if (cell_gap2(g, cx, cy, cz, q) > worst) return;
    for (Py_ssize_t s = g->start[c]; s < g->start[c + 1]; s++) {
        Py_ssize_t i = g->sorted[s];
        const double *p = g->ref + 3 * i;
        double dx = p[0] - q[0], dy = p[1] - q[1], dz = p[2] - q[2];
        double d = (dx * dx + dy * dy) + dz * dz;
        if (d <= limit2) *have = offer(bd, bi, *have, k, d, (int64_t)i);
    }
}

static Py_ssize_t max_ss(Py_ssize_t a, Py_ssize_t b) { return a > b ? a : b; }
static Py_ssize_t min_ss(Py_ssize_t a, Py_ssize_t b) { return a < b ? a : b; }

static void query_one(const Grid *g, const double *q, Py_ssize_t k, double limit2, double *bd, int64_t *bi) {
    Py_ssize_t c[3], reach = 0, first = 0;
    for (int a = 0; a < 3; a++) {
        c[a] = cell_coord(q[a], g->origin[a], g->cell);
        Py_ssize_t below = -c[a], above = c[a] - (g->dims[a] - 1);
        first = max_ss(first, max_ss(below, above));          /* rings before this hold no cell */
        reach = max_ss(reach, max_ss(c[a], g->dims[a] - 1 - c[a])); /* this ring covers the grid */
    }
    Py_ssize_t have = 0;
    for (Py_ssize_t r = first; r <= reach; r++) {
        Py_ssize_t z0 = max_ss(c[2] - r, 0), z1 = min_ss(c[2] + r, g->dims[2] - 1);
        Py_ssize_t y0 = max_ss(c[1] - r, 0), y1 = min_ss(c[1] + r, g->dims[1] - 1);
        for (Py_ssize_t z = z0; z <= z1; z++) {
            int z_edge = z == c[2] - r || z == c[2] + r;
            for (Py_ssize_t y = y0; y <= y1; y++) {
                int edge = z_edge || y == c[1] - r || y == c[1] + r;
                if (edge) {
                    for (Py_ssize_t x = max_ss(c[0] - r, 0); x <= min_ss(c[0] + r, g->dims[0] - 1); x++)
                        scan_cell(g, x, y, z, q, bd, bi, &have, k, limit2);
                } else {
                    if (c[0] - r >= 0 && c[0] - r < g->dims[0]) scan_cell(g, c[0] - r, y, z, q, bd, bi, &have, k, limit2);
                    if (r > 0 && c[0] + r >= 0 && c[0] + r < g->dims[0]) scan_cell(g, c[0] + r, y, z, q, bd, bi, &have, k, limit2);
                }
            }
        }
        /* every unvisited point lies outside the cube of rings <= r, at least `bound` away */
        double bound = INFINITY;
        for (int a = 0; a < 3; a++) {
            double lo = q[a] - (g->origin[a] + (double)(c[a] - r) * g->cell);
            double hi = g->origin[a] + (double)(c[a] + r + 1) * g->cell - q[a];
            if (lo < bound) bound = lo;
            if (hi < bound) bound = hi;
        }
        if (bound > 0.0) {
            double outside2 = bound * bound * (1.0 - 1e-12);
            if ((have == k ? bd[k - 1] : limit2) < outside2) break;
        }
    }
    for (Py_ssize_t t = have; t < k; t++) { /* fewer than k within the limit */
        bd[t] = INFINITY;
        bi[t] = (int64_t)g->m;
    }
}

PyDoc_STRVAR(knn_doc,
    "knn(ref, queries, k, limit, out_dist, out_index)\n\n"
    "ref: (M, 3) float64; queries: (Q, 3) float64; k <= M; out_dist: (Q, k) float64 and\n"
    "out_index: (Q, k) int64, filled with the k nearest rows of ref by (distance, row)\n"
    "among those at most `limit` away (inf: all); missing neighbours get inf and row M.");

static PyObject *knn(PyObject *self, PyObject *args) {
    Py_buffer ref, queries, out_dist, out_index;
    Py_ssize_t k;
    double limit;
    if (!PyArg_ParseTuple(args, "y*y*ndw*w*", &ref, &queries, &k, &limit, &out_dist, &out_index)) return NULL;
    PyObject *result = NULL;
    Grid g = {0};
    Py_ssize_t m = ref.len / (3 * (Py_ssize_t)sizeof(double));
    Py_ssize_t q = queries.len / (3 * (Py_ssize_t)sizeof(double));
    if (k < 1 || k > m || check_buffer(&ref, "ref", 3 * m, sizeof(double)) ||
        check_buffer(&queries, "queries", 3 * q, sizeof(double)) ||
        check_buffer(&out_dist, "out_dist", q * k, sizeof(double)) ||
        check_buffer(&out_index, "out_index", q * k, sizeof(int64_t))) {
        if (!PyErr_Occurred()) PyErr_SetString(PyExc_ValueError, "knn: k must be between 1 and the reference points");
        goto done;
    }
    int failed;
    Py_BEGIN_ALLOW_THREADS
    double limit2 = limit < INFINITY ? limit * limit : INFINITY;
    failed = grid_build(&g, ref.buf, m);
    if (!failed) {
        double *dist = out_dist.buf;
        int64_t *index = out_index.buf;
        const double *qs = queries.buf;
        for (Py_ssize_t j = 0; j < q; j++) {
            query_one(&g, qs + 3 * j, k, limit2, dist + j * k, index + j * k);
            for (Py_ssize_t t = 0; t < k; t++) dist[j * k + t] = sqrt(dist[j * k + t]);
        }
    }
    Py_END_ALLOW_THREADS
    if (failed) {
        PyErr_NoMemory();
        goto done;
    }
    Py_INCREF(Py_None);
    result = Py_None;
done:
    free(g.start);
    free(g.sorted);
    PyBuffer_Release(&ref);
    PyBuffer_Release(&queries);
    PyBuffer_Release(&out_dist);
    PyBuffer_Release(&out_index);
    return result;
}

static PyMethodDef methods[] = {
    {"fps", fps, METH_VARARGS, fps_doc},
    {"knn", knn, METH_VARARGS, knn_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_kernels", "Compiled loops of escape_cli.core (see _kernels.c).", -1, methods,
};

PyMODINIT_FUNC PyInit__kernels(void) { return PyModule_Create(&module); }
