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
    klu_numeric *active;  /* a kept factorization (fx_store_use) the solves use, else NULL */
    void *active_work;    /* the store's workspace for it */
} fx_klu;

/*
 * Factor store: the factorizations a forward run keeps for the adjoint's backward pass (one
 * per tape column, where it fits a byte budget), owned by the caller (Python: an integer
 * handle wrapped in an object that frees it; flexmbs.adjoint.FactorStore). Columns without a
 * kept factorization are refactored by the backward pass. Dense: LU values and pivots; KLU: a
 * deep copy of the numeric object (its structure and values; the solve workspace is the
 * store's), valid with the symbolic analysis recorded at the first put (checked at use).
 */
#define FX_STORE_MAGIC 0x46584653  /* "FXFS" */

typedef struct {
    int kind;             /* 1 dense, 2 KLU */
    void *lu;             /* dense: n*n doubles; KLU: klu_numeric * (deep copy) */
    int *ipiv;            /* dense pivots */
    int exact;            /* 1: the matrix of the converged state (to rounding), 0: of the
                             last Newton iterate (within the tolerance of it) */
    double bytes;
} fx_entry;

typedef struct {
    int magic;
    int ncol;
    int n;                /* order of the factored matrices (0: none put yet) */
    double budget;        /* bytes allowed */
    double used;          /* bytes held */
    int kept;             /* entries held */
    fx_entry *e;          /* ncol entries */
    /* KLU: the symbolic analysis the numerics belong to */
    int nblocks;
    int *Q, *R;
    void *work;           /* solve workspace shared by the kept numerics */
    size_t worksize;
} fx_store;

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
    h->active = NULL;
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

/* The numeric object the solves use: a kept one (fx_store_use) or the handle's own. */
static klu_numeric *solve_numeric(fx_klu *h)
{
    if (h->active != NULL) {
        h->active->Work = h->active_work;
        h->active->Xwork = h->active_work;
        h->active->Iwork = (int *) h->active_work;
        return h->active;
    }
    return h->numeric;
}

/* Solve A x = b in place for nrhs right-hand sides stored column by column (leading dim n). */
int fx_klu_solve(void *handle, double *b, int nrhs)
{
    fx_klu *h = (fx_klu *) handle;
    klu_numeric *num;
    if (h == NULL) return 3;
    num = solve_numeric(h);
    if (num == NULL) return 3;
    if (!klu_solve(h->symbolic, num, h->n, nrhs, b, &h->common)) {
        int s = map_status(&h->common);
        return s == 0 ? 3 : s;
    }
    return 0;
}

/* Solve A^T x = b in place (the adjoint's transposed solves), same layout as fx_klu_solve. */
int fx_klu_tsolve(void *handle, double *b, int nrhs)
{
    fx_klu *h = (fx_klu *) handle;
    klu_numeric *num;
    if (h == NULL) return 3;
    num = solve_numeric(h);
    if (num == NULL) return 3;
    if (!klu_tsolve(h->symbolic, num, h->n, nrhs, b, &h->common)) {
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

/* ---- factor store ----------------------------------------------------------------- */

static fx_store *store_of(void *p)
{
    fx_store *s = (fx_store *) p;
    return (s != NULL && s->magic == FX_STORE_MAGIC) ? s : NULL;
}

static void free_numeric_copy(klu_numeric *c)
{
    int b;
    if (c == NULL) return;
    free(c->Pnum); free(c->Pinv); free(c->Lip); free(c->Uip); free(c->Llen); free(c->Ulen);
    if (c->LUbx != NULL) {
        for (b = 0; b < c->nblocks; ++b) free(c->LUbx[b]);
    }
    free(c->LUbx); free(c->LUsize); free(c->Udiag); free(c->Rs);
    free(c->Offp); free(c->Offi); free(c->Offx);
    free(c);
}

static void entry_clear(fx_store *s, int col)
{
    fx_entry *e = &s->e[col];
    if (e->kind == 1) {
        free(e->lu);
        free(e->ipiv);
    } else if (e->kind == 2) {
        free_numeric_copy((klu_numeric *) e->lu);
    }
    if (e->kind != 0) {
        s->used -= e->bytes;
        s->kept -= 1;
    }
    e->kind = 0;
    e->exact = 0;
    e->lu = NULL;
    e->ipiv = NULL;
    e->bytes = 0;
}

/* A store of ncol (>= 1) columns holding at most budget bytes of factors; NULL: no memory. */
void *fx_store_create(int ncol, double budget)
{
    fx_store *s;
    if (ncol < 1) return NULL;
    s = (fx_store *) calloc(1, sizeof(fx_store));
    if (s == NULL) return NULL;
    s->e = (fx_entry *) calloc((size_t) ncol, sizeof(fx_entry));
    if (s->e == NULL) { free(s); return NULL; }
    s->magic = FX_STORE_MAGIC;
    s->ncol = ncol;
    s->budget = budget;
    return (void *) s;
}

/* Drop what column col (0-based) holds. */
void fx_store_drop(void *p, int col)
{
    fx_store *s = store_of(p);
    if (s == NULL || col < 0 || col >= s->ncol) return;
    entry_clear(s, col);
}

/* Drop every kept factorization (a new forward run). */
void fx_store_reset(void *p)
{
    fx_store *s = store_of(p);
    int k;
    if (s == NULL) return;
    for (k = 0; k < s->ncol; ++k) entry_clear(s, k);
    free(s->Q); free(s->R); free(s->work);
    s->Q = s->R = NULL;
    s->work = NULL;
    s->worksize = 0;
    s->n = 0;
    s->nblocks = 0;
    s->used = 0;
    s->kept = 0;
}

void fx_store_free(void *p)
{
    fx_store *s = store_of(p);
    if (s == NULL) return;
    fx_store_reset(p);
    free(s->e);
    s->magic = 0;
    free(s);
}

/* [entries kept, bytes held, budget, columns] */
void fx_store_info(void *p, double *out)
{
    fx_store *s = store_of(p);
    out[0] = out[1] = out[2] = out[3] = 0;
    if (s == NULL) return;
    out[0] = s->kept;
    out[1] = s->used;
    out[2] = s->budget;
    out[3] = s->ncol;
}

/* Whether column col (0-based) holds a factorization of order n and kind. */
int fx_store_has(void *p, int col, int kind, int n)
{
    fx_store *s = store_of(p);
    if (s == NULL || col < 0 || col >= s->ncol || s->n != n) return 0;
    return s->e[col].kind == kind;
}

/* Keep a dense LU (n x n, column-major) and its pivots in column col (exact: see fx_entry).
 * 0: kept, 1: no room. */
int fx_store_put_dense(void *p, int col, int n, const double *lu, const int *ipiv, int exact)
{
    fx_store *s = store_of(p);
    double bytes = 8.0 * (double) n * n + 4.0 * n;
    fx_entry *e;
    if (s == NULL || col < 0 || col >= s->ncol) return 1;
    entry_clear(s, col);
    if (s->n != 0 && s->n != n) return 1;
    if (s->used + bytes > s->budget) return 1;
    e = &s->e[col];
    e->lu = malloc(sizeof(double) * (size_t) n * (size_t) n);
    e->ipiv = (int *) malloc(sizeof(int) * (size_t) n);
    if (e->lu == NULL || e->ipiv == NULL) {
        free(e->lu); free(e->ipiv);
        e->lu = NULL; e->ipiv = NULL;
        return 1;
    }
    memcpy(e->lu, lu, sizeof(double) * (size_t) n * (size_t) n);
    memcpy(e->ipiv, ipiv, sizeof(int) * (size_t) n);
    e->kind = 1;
    e->exact = exact;
    e->bytes = bytes;
    s->n = n;
    s->used += bytes;
    s->kept += 1;
    return 0;
}

/* Copy the dense LU and pivots of column col back. -1: none kept there; else its exact flag. */
int fx_store_get_dense(void *p, int col, int n, double *lu, int *ipiv)
{
    fx_store *s = store_of(p);
    if (!fx_store_has(p, col, 1, n)) return -1;
    memcpy(lu, s->e[col].lu, sizeof(double) * (size_t) n * (size_t) n);
    memcpy(ipiv, s->e[col].ipiv, sizeof(int) * (size_t) n);
    return s->e[col].exact;
}

static void *dup(const void *src, size_t bytes)
{
    void *d;
    if (src == NULL) return NULL;
    d = malloc(bytes > 0 ? bytes : 1);
    if (d != NULL) memcpy(d, src, bytes);
    return d;
}

/* Keep a deep copy of the handle's current KLU factorization in column col (exact: see
 * fx_entry). 0: kept, 1: no room (budget or memory) or no factorization held. */
int fx_klu_keep(void *handle, void *p, int col, int exact)
{
    fx_klu *h = (fx_klu *) handle;
    fx_store *s = store_of(p);
    klu_numeric *a, *c;
    double bytes;
    size_t n, nb, units = 0;
    int b, nzoff;
    if (h == NULL || s == NULL || h->numeric == NULL || col < 0 || col >= s->ncol) return 1;
    entry_clear(s, col);
    a = h->numeric;
    n = (size_t) a->n;
    nb = (size_t) a->nblocks;
    nzoff = a->nzoff;
    /* LUsize is set only for the blocks with factors (not for 1 x 1 blocks) */
    for (b = 0; b < a->nblocks; ++b) if (a->LUbx[b] != NULL) units += a->LUsize[b];
    bytes = 8.0 * units + 4.0 * (6.0 * n + (n + 1) + nzoff) + 8.0 * (2.0 * n + nzoff)
            + 16.0 * nb + sizeof(klu_numeric);
    if (s->n != 0 && s->n != h->n) return 1;
    if (s->used + bytes > s->budget) return 1;
    if (s->Q == NULL) {
        /* the symbolic analysis these numerics belong to (checked by fx_store_use) */
        s->Q = (int *) dup(h->symbolic->Q, sizeof(int) * n);
        s->R = (int *) dup(h->symbolic->R, sizeof(int) * (nb + 1));
        if (s->Q == NULL || s->R == NULL) {
            free(s->Q); free(s->R); s->Q = s->R = NULL;
            return 1;
        }
        s->nblocks = h->symbolic->nblocks;
    }
    if (a->worksize > s->worksize) {
        void *w = realloc(s->work, a->worksize);
        if (w == NULL) return 1;
        s->work = w;
        s->worksize = a->worksize;
    }
    c = (klu_numeric *) calloc(1, sizeof(klu_numeric));
    if (c == NULL) return 1;
    *c = *a;
    c->Pnum = c->Pinv = c->Lip = c->Uip = c->Llen = c->Ulen = NULL;
    c->LUbx = NULL; c->LUsize = NULL; c->Udiag = NULL; c->Rs = NULL;
    c->Offp = c->Offi = NULL; c->Offx = NULL;
    c->Work = c->Xwork = NULL; c->Iwork = NULL;
    c->worksize = 0;
    c->Pnum = (int *) dup(a->Pnum, sizeof(int) * n);
    c->Pinv = (int *) dup(a->Pinv, sizeof(int) * n);
    c->Lip = (int *) dup(a->Lip, sizeof(int) * n);
    c->Uip = (int *) dup(a->Uip, sizeof(int) * n);
    c->Llen = (int *) dup(a->Llen, sizeof(int) * n);
    c->Ulen = (int *) dup(a->Ulen, sizeof(int) * n);
    c->LUsize = (size_t *) dup(a->LUsize, sizeof(size_t) * nb);
    c->LUbx = (void **) calloc(nb > 0 ? nb : 1, sizeof(void *));
    c->Udiag = dup(a->Udiag, sizeof(double) * n);
    c->Rs = (double *) dup(a->Rs, sizeof(double) * n);
    c->Offp = (int *) dup(a->Offp, sizeof(int) * (n + 1));
    c->Offi = (int *) dup(a->Offi, sizeof(int) * (size_t) nzoff);
    c->Offx = dup(a->Offx, sizeof(double) * (size_t) nzoff);
    if (c->Pnum == NULL || c->Pinv == NULL || c->Lip == NULL || c->Uip == NULL
        || c->Llen == NULL || c->Ulen == NULL || c->LUsize == NULL || c->LUbx == NULL
        || c->Udiag == NULL || (a->Rs != NULL && c->Rs == NULL) || c->Offp == NULL
        || c->Offi == NULL || c->Offx == NULL) {
        free_numeric_copy(c);
        return 1;
    }
    for (b = 0; b < a->nblocks; ++b) {
        if (a->LUbx[b] == NULL) continue;
        c->LUbx[b] = dup(a->LUbx[b], 8 * a->LUsize[b]);
        if (c->LUbx[b] == NULL) {
            free_numeric_copy(c);
            return 1;
        }
    }
    s->e[col].kind = 2;
    s->e[col].exact = exact;
    s->e[col].lu = (void *) c;
    s->e[col].bytes = bytes;
    s->n = h->n;
    s->used += bytes;
    s->kept += 1;
    return 0;
}

/* Make the handle's solves use the factorization kept in column col (until the next
 * fx_klu_factor). -1: none kept there, or kept with another symbolic analysis; else its
 * exact flag. */
int fx_klu_use(void *handle, void *p, int col)
{
    fx_klu *h = (fx_klu *) handle;
    fx_store *s = store_of(p);
    int k;
    if (h == NULL || s == NULL || !fx_store_has(p, col, 2, h->n)) return -1;
    if (s->nblocks != h->symbolic->nblocks) return -1;
    for (k = 0; k < h->n; ++k) if (s->Q[k] != h->symbolic->Q[k]) return -1;
    for (k = 0; k <= s->nblocks; ++k) if (s->R[k] != h->symbolic->R[k]) return -1;
    h->active = (klu_numeric *) s->e[col].lu;
    h->active_work = s->work;
    return s->e[col].exact;
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
