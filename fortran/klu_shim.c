/*
 * klu_shim.c: a thin C layer between the Fortran core and SuiteSparse KLU.
 *
 * Every factorization lives in a handle owned by the caller (an opaque
 * pointer kept in a local variable of the Fortran simulation routine); the
 * shim has no static or global state, so two models factorized in the same
 * process, or in parallel threads, never interfere.
 *
 * Status codes (returned to Fortran):
 *   0  success
 *   1  matrix numerically singular (zero pivot or pivot ratio below 1e-14)
 *   2  out of memory
 *   3  invalid input (pattern) or other KLU failure
 *   4  non-finite value in the matrix
 */
#include <math.h>
#include <stdlib.h>
#include <string.h>
#include <klu.h>

typedef struct {
    int n;
    int nnz;
    int *ap;              /* column pointers, 0-based, copied */
    int *ai;              /* row indices, 0-based, copied */
    klu_common common;
    klu_symbolic *symbolic;
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

/* Create a handle and run the symbolic analysis of the pattern (once per simulation). */
void *fx_klu_create(int n, int nnz, const int *ap, const int *ai, int *status)
{
    fx_klu *h = (fx_klu *) calloc(1, sizeof(fx_klu));
    if (h == NULL) { *status = 2; return NULL; }
    h->n = n;
    h->nnz = nnz;
    h->ap = (int *) malloc(sizeof(int) * (size_t) (n + 1));
    h->ai = (int *) malloc(sizeof(int) * (size_t) (nnz > 0 ? nnz : 1));
    if (h->ap == NULL || h->ai == NULL) {
        free(h->ap); free(h->ai); free(h);
        *status = 2;
        return NULL;
    }
    memcpy(h->ap, ap, sizeof(int) * (size_t) (n + 1));
    memcpy(h->ai, ai, sizeof(int) * (size_t) nnz);
    klu_defaults(&h->common);
    h->symbolic = klu_analyze(n, h->ap, h->ai, &h->common);
    if (h->symbolic == NULL) {
        *status = (h->common.status == KLU_OUT_OF_MEMORY) ? 2 : 3;
        free(h->ap); free(h->ai); free(h);
        return NULL;
    }
    *status = 0;
    return (void *) h;
}

static int pivots_ok(fx_klu *h)
{
    /* klu_rcond: min |U_ii| / max |U_ii|, cheap; flags a numerically singular matrix */
    if (!klu_rcond(h->symbolic, h->numeric, &h->common)) return 0;
    if (!(h->common.rcond > 1e-14)) return 0;    /* also catches NaN */
    return 1;
}

/* Numeric factorization with the values ax (CSC order of the pattern).
 * The first call factors; later calls refactor with the same pivot order,
 * and fall back to a fresh factorization if the refactored pivots are poor. */
int fx_klu_factor(void *handle, const double *ax)
{
    fx_klu *h = (fx_klu *) handle;
    int k;
    if (h == NULL) return 3;
    for (k = 0; k < h->nnz; ++k) {
        if (!isfinite(ax[k])) return 4;
    }
    if (h->numeric != NULL) {
        if (klu_refactor(h->ap, h->ai, (double *) ax, h->symbolic, h->numeric, &h->common)
            && pivots_ok(h)) {
            return 0;
        }
        klu_free_numeric(&h->numeric, &h->common);
        h->numeric = NULL;
    }
    h->common.status = KLU_OK;
    h->numeric = klu_factor(h->ap, h->ai, (double *) ax, h->symbolic, &h->common);
    if (h->numeric == NULL) {
        int s = map_status(&h->common);
        return s == 0 ? 3 : s;
    }
    if (h->common.status == KLU_SINGULAR || !pivots_ok(h)) return 1;
    return 0;
}

/* Solve A x = b in place for nrhs right-hand sides stored column by column (leading dim n). */
int fx_klu_solve(void *handle, double *b, int nrhs)
{
    fx_klu *h = (fx_klu *) handle;
    if (h == NULL || h->numeric == NULL) return 3;
    if (!klu_solve(h->symbolic, h->numeric, h->n, nrhs, b, &h->common)) {
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
    if (!klu_tsolve(h->symbolic, h->numeric, h->n, nrhs, b, &h->common)) {
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
    if (h->symbolic != NULL) klu_free_symbolic(&h->symbolic, &h->common);
    free(h->ap);
    free(h->ai);
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
