/*
 * klu_shim.c: a thin C layer between the Fortran core and SuiteSparse KLU.
 *
 * Every factorization lives in a handle owned by the caller (an opaque
 * pointer kept in a local variable of the Fortran simulation routine); the
 * shim has no static or global state, so two models factorized in the same
 * process, or in parallel threads, never interfere.
 *
 * The symbolic analysis of a pattern (ordering and block structure: klu_analyze)
 * can also live in an analysis object of its own (fx_klu_analyze), created once
 * per model by Python and handed to every simulation of that model: its handles
 * then borrow it instead of analysing the pattern again. KLU only reads a
 * symbolic analysis after klu_analyze, so simulations in parallel threads may
 * share one.
 *
 * Status codes (returned to Fortran):
 *   0  success
 *   1  matrix numerically singular (zero pivot or pivot ratio below 1e-14)
 *   2  out of memory
 *   3  invalid input (pattern) or other KLU failure
 *   4  non-finite value in the matrix
 */
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <klu.h>

typedef struct {
    int n;
    int nnz;
    int *ap;              /* column pointers, 0-based, copied */
    int *ai;              /* row indices, 0-based, copied */
    klu_symbolic *symbolic;
} fx_klu_analysis;

typedef struct {
    int n;
    int nnz;
    fx_klu_analysis *analysis;   /* the pattern and its symbolic analysis */
    int owns_analysis;           /* 1: made by this handle (freed with it), 0: borrowed */
    klu_common common;
    klu_numeric *numeric;
} fx_klu;

static int map_status(const klu_common *c)
{
    switch (c->status) {
    case KLU_OK: return 0;
    case KLU_SINGULAR: return 1;
    case KLU_OUT_OF_MEMORY: return 2;
    default: return 3;
    }
}

/* The symbolic analysis of a pattern, as an object of its own (see the header).
 * status: 0, 2 out of memory, 3 invalid pattern. Free with fx_klu_analysis_free. */
void *fx_klu_analyze(int n, int nnz, const int *ap, const int *ai, int *status)
{
    klu_common common;
    fx_klu_analysis *a = (fx_klu_analysis *) calloc(1, sizeof(fx_klu_analysis));
    if (a == NULL) { *status = 2; return NULL; }
    a->n = n;
    a->nnz = nnz;
    a->ap = (int *) malloc(sizeof(int) * (size_t) (n + 1));
    a->ai = (int *) malloc(sizeof(int) * (size_t) (nnz > 0 ? nnz : 1));
    if (a->ap == NULL || a->ai == NULL) {
        free(a->ap); free(a->ai); free(a);
        *status = 2;
        return NULL;
    }
    memcpy(a->ap, ap, sizeof(int) * (size_t) (n + 1));
    memcpy(a->ai, ai, sizeof(int) * (size_t) nnz);
    klu_defaults(&common);
    a->symbolic = klu_analyze(n, a->ap, a->ai, &common);
    if (a->symbolic == NULL) {
        *status = (common.status == KLU_OUT_OF_MEMORY) ? 2 : 3;
        free(a->ap); free(a->ai); free(a);
        return NULL;
    }
    *status = 0;
    return (void *) a;
}

/* Release an analysis object. Safe on NULL. No handle may borrow it any more. */
void fx_klu_analysis_free(void *analysis)
{
    klu_common common;
    fx_klu_analysis *a = (fx_klu_analysis *) analysis;
    if (a == NULL) return;
    klu_defaults(&common);
    if (a->symbolic != NULL) klu_free_symbolic(&a->symbolic, &common);
    free(a->ap);
    free(a->ai);
    free(a);
}

/* Create a handle for the pattern (ap, ai). With shared == NULL it runs the symbolic
 * analysis itself (once per simulation); otherwise it borrows the analysis object
 * `shared`, which must be of this very pattern (status 3 if not). */
void *fx_klu_create(int n, int nnz, const int *ap, const int *ai, void *shared, int *status)
{
    fx_klu_analysis *a = (fx_klu_analysis *) shared;
    fx_klu *h;
    if (a != NULL && (a->n != n || a->nnz != nnz
                      || memcmp(a->ap, ap, sizeof(int) * (size_t) (n + 1)) != 0
                      || memcmp(a->ai, ai, sizeof(int) * (size_t) nnz) != 0)) {
        *status = 3;
        return NULL;
    }
    h = (fx_klu *) calloc(1, sizeof(fx_klu));
    if (h == NULL) { *status = 2; return NULL; }
    if (a == NULL) {
        a = (fx_klu_analysis *) fx_klu_analyze(n, nnz, ap, ai, status);
        if (a == NULL) { free(h); return NULL; }
        h->owns_analysis = 1;
    }
    h->n = n;
    h->nnz = nnz;
    h->analysis = a;
    klu_defaults(&h->common);
    *status = 0;
    return (void *) h;
}

/* 1 if the handle ran its own symbolic analysis, 0 if it borrowed one. */
int fx_klu_analysed(void *handle)
{
    fx_klu *h = (fx_klu *) handle;
    return (h != NULL && h->owns_analysis) ? 1 : 0;
}

/* 1 if no value is Inf or NaN (exponent bits all ones): a branch-free OR over the bit
 * patterns, which the compiler vectorizes (an isfinite loop with an early return was
 * 1.8 % of an adjoint evaluation's samples under perf on the 2-core reference machine) */
static int all_finite(const double *x, int n)
{
    const uint64_t expo = 0x7ff0000000000000ULL;
    uint64_t bad = 0;
    int k;
    for (k = 0; k < n; ++k) {
        uint64_t b;
        memcpy(&b, &x[k], sizeof b);
        bad |= (uint64_t) ((b & expo) == expo);
    }
    return bad == 0;
}

static int pivots_ok(fx_klu *h)
{
    /* klu_rcond: min |U_ii| / max |U_ii|, cheap; flags a numerically singular matrix */
    if (!klu_rcond(h->analysis->symbolic, h->numeric, &h->common)) return 0;
    if (!(h->common.rcond > 1e-14)) return 0;    /* also catches NaN */
    return 1;
}

/* Refactor with the held pivots and row scaling `scale` (KLU's Common.scale: -1 none and
 * no index check, 2 max-abs rows); 1 if it succeeded with acceptable pivots. */
static int refactor(fx_klu *h, const double *ax, int scale)
{
    h->common.scale = scale;
    return klu_refactor(h->analysis->ap, h->analysis->ai, (double *) ax, h->analysis->symbolic,
                        h->numeric, &h->common)
           && pivots_ok(h);
}

/* Numeric factorization with the values ax (CSC order of the pattern).
 * The first call factors; later calls refactor with the same pivot order,
 * and fall back to a fresh factorization if the refactored pivots are poor.
 *
 * Pivots are chosen by klu_factor on the row-scaled matrix (KLU's default scaling), but
 * the factors the solves use are always those of a refactorization without row scaling
 * (scale = -1, which also skips KLU's index check: the pattern was checked when the
 * handle was made): with fixed pivots the factors of D A are D L D^-1 and D U, so the
 * scaling changes rounding only, and KLU recomputing it at every refactorization was
 * 5.3 % of an adjoint evaluation's samples (perf, 2-core reference machine; without it: simulations
 * 7-8 %, adjoint evaluations 6-10 % faster, interleaved, tapered tubes at 8 and 32
 * elements per arm). A fresh factorization is refactored once without scaling too, so
 * that a run's factors do not depend on which of its factorizations were fresh: a
 * checkpointed adjoint's segment, which starts with a fresh one where the first run
 * refactored, repeats the first run bit for bit (tests/test_adjoint_checkpoints.py). */
int fx_klu_factor(void *handle, const double *ax)
{
    fx_klu *h = (fx_klu *) handle;
    if (h == NULL) return 3;
    if (!all_finite(ax, h->nnz)) return 4;
    if (h->numeric != NULL) {
        if (refactor(h, ax, -1)) return 0;
        klu_free_numeric(&h->numeric, &h->common);
        h->numeric = NULL;
    }
    h->common.scale = 2;
    h->common.status = KLU_OK;
    h->numeric = klu_factor(h->analysis->ap, h->analysis->ai, (double *) ax,
                            h->analysis->symbolic, &h->common);
    if (h->numeric == NULL) {
        int s = map_status(&h->common);
        return s == 0 ? 3 : s;
    }
    if (h->common.status == KLU_SINGULAR || !pivots_ok(h)) return 1;
    if (refactor(h, ax, -1)) return 0;
    /* the unscaled factors' pivots failed the check: keep the scaled ones */
    return refactor(h, ax, 2) ? 0 : 1;
}

/* Solve A x = b in place for nrhs right-hand sides stored column by column (leading dim n). */
int fx_klu_solve(void *handle, double *b, int nrhs)
{
    fx_klu *h = (fx_klu *) handle;
    if (h == NULL || h->numeric == NULL) return 3;
    if (!klu_solve(h->analysis->symbolic, h->numeric, h->n, nrhs, b, &h->common)) {
        int s = map_status(&h->common);
        return s == 0 ? 3 : s;
    }
    return 0;
}

/* Solve A^T x = b in place (the adjoint's transposed solves), same layout as fx_klu_solve. */
int fx_klu_tsolve(void *handle, double *b, int nrhs)
{
    fx_klu *h = (fx_klu *) handle;
    if (h == NULL || h->numeric == NULL) return 3;
    if (!klu_tsolve(h->analysis->symbolic, h->numeric, h->n, nrhs, b, &h->common)) {
        int s = map_status(&h->common);
        return s == 0 ? 3 : s;
    }
    return 0;
}

/* Release everything the handle owns. Safe on NULL. */
void fx_klu_free(void *handle)
{
    fx_klu *h = (fx_klu *) handle;
    if (h == NULL) return;
    if (h->numeric != NULL) klu_free_numeric(&h->numeric, &h->common);
    if (h->owns_analysis) fx_klu_analysis_free(h->analysis);
    free(h);
}

#ifdef FLEXMBS_HAVE_OPENBLAS
void openblas_set_num_threads(int);
#endif

/* Run the BLAS/LAPACK used by the core on one thread. The dense systems of
 * the core are small (tens of unknowns) and factorized thousands of times per
 * simulation: a BLAS thread pool only adds synchronisation latency there, and
 * batch runs parallelise over designs instead. Returns 1 if the setting was
 * applied (OpenBLAS), 0 if the BLAS offers no such control. */
int fx_blas_single_thread(void)
{
#ifdef FLEXMBS_HAVE_OPENBLAS
    openblas_set_num_threads(1);
    return 1;
#else
    return 0;
#endif
}
