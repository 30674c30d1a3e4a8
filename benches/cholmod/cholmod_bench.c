/*
 * cholmod_bench — CHOLMOD numeric Cholesky timing for factord's linear-algebra benchmarks.
 *
 *   cholmod_bench --matrix H.mtx [--repeat 50] [--mode supernodal|simplicial|auto]
 *                 [--ordering amd|metis|nesdis|best|default]
 *
 * Reads a symmetric positive-definite matrix in Matrix Market coordinate format (one triangle
 * stored, upper or lower; cholmod_read_sparse handles both and returns a symmetric matrix), runs
 * cholmod_analyze once, then cholmod_factorize N times on the same factor object, which is what an
 * iterative solver such as Ceres does between iterations (symbolic analysis reused, numeric
 * factor overwritten in place).
 *
 * WHAT IS TIMED (wall clock, clock_gettime(CLOCK_MONOTONIC)):
 *   analyze_seconds       one cholmod_analyze (fill-reducing ordering + symbolic factorisation)
 *   first_numeric_seconds the first cholmod_factorize (also allocates the numeric factor); NOT
 *                         part of numeric_seconds_runs
 *   numeric_seconds_runs  each of the following N cholmod_factorize calls, numeric only
 *   numeric_seconds       median of numeric_seconds_runs
 * Not timed: reading the file, cholmod_start, the solve used for the residual check.
 *
 * Orderings: amd / metis / nesdis use exactly that method (nmethods = 1, weighted postorder);
 * best tries all of CHOLMOD's methods (nmethods = 9) and keeps the one with the least fill;
 * default is CHOLMOD's own default strategy (nmethods = 0: AMD, and METIS if AMD's fill is high).
 *
 * BLAS threading: CHOLMOD's supernodal kernels call BLAS/LAPACK. For a single-core comparison
 * OPENBLAS_NUM_THREADS / OMP_NUM_THREADS / MKL_NUM_THREADS / GOTO_NUM_THREADS are forced to 1
 * (unless the caller set them). OpenBLAS/MKL read these when the library is loaded, which for a
 * dynamically linked BLAS happens before main(), so setenv() alone is too late: main() sets them
 * and re-execs itself once (run_single_threaded).
 * Which BLAS is used is reported ("blas" field, from /proc/self/maps).
 */

#define _GNU_SOURCE
#include <errno.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <unistd.h>

#include <cholmod.h>

static double now_seconds(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

static int cmp_double(const void *a, const void *b) {
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

static double median(const double *v, int n) {
    double *s = malloc((size_t)n * sizeof *s);
    memcpy(s, v, (size_t)n * sizeof *s);
    qsort(s, (size_t)n, sizeof *s, cmp_double);
    double m = (n % 2) ? s[n / 2] : 0.5 * (s[n / 2 - 1] + s[n / 2]);
    free(s);
    return m;
}

static void json_string(const char *s) {
    putchar('"');
    for (; *s; ++s) {
        unsigned char c = (unsigned char)*s;
        if (c == '"' || c == '\\') printf("\\%c", c);
        else if (c < 0x20) printf("\\u%04x", c);
        else putchar(c);
    }
    putchar('"');
}

static void json_number(double x) {
    if (isfinite(x)) printf("%.9g", x);
    else printf("null");
}

/* Print an error object on stdout (so callers always get JSON) and exit. */
static void fail(const char *matrix, const char *msg) {
    printf("{\"system\":\"cholmod\",\"matrix\":");
    json_string(matrix ? matrix : "");
    printf(",\"error\":");
    json_string(msg);
    printf("}\n");
    exit(1);
}

static void usage(const char *msg) {
    fprintf(stderr,
            "error: %s\n"
            "usage: cholmod_bench --matrix H.mtx [--repeat 50] [--mode supernodal|simplicial|auto]\n"
            "                     [--ordering amd|metis|nesdis|best|default]\n",
            msg);
    exit(2);
}

/* Make BLAS single-threaded. Thread-count variables are read by OpenBLAS/MKL at load time, which
 * precedes main() for a dynamically linked BLAS, so if they were not already set we set them and
 * re-exec ourselves once. */
static void run_single_threaded(char **argv) {
    static const char *vars[] = {"OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS",
                                 "GOTO_NUM_THREADS"};
    int changed = 0;
    for (size_t k = 0; k < sizeof vars / sizeof vars[0]; ++k) {
        if (!getenv(vars[k])) {
            setenv(vars[k], "1", 1);
            changed = 1;
        }
    }
    if (changed && !getenv("CHOLMOD_BENCH_REEXEC")) {
        setenv("CHOLMOD_BENCH_REEXEC", "1", 1);
        execv("/proc/self/exe", argv);
        /* If re-exec fails we carry on; the variables are set for anything loaded later. */
    }
}

/* Name of the BLAS shared object mapped into this process (best effort). */
static void detect_blas(char *out, size_t len) {
    snprintf(out, len, "unknown");
    FILE *f = fopen("/proc/self/maps", "r");
    if (!f) return;
    char line[4096];
    while (fgets(line, sizeof line, f)) {
        char *p = strrchr(line, '/');
        if (!p) continue;
        ++p;
        p[strcspn(p, "\n")] = 0;
        if (strstr(p, "openblas") || strstr(p, "mkl_rt") || strstr(p, "libblis") ||
            strstr(p, "libblas.so") || strstr(p, "libatlas") || strstr(p, "libtatlas") ||
            strstr(p, "libsatlas")) {
            /* resolve the Debian alternatives symlink to show the real implementation */
            char path[4096], real[4096];
            char *slash = strchr(line, '/');
            snprintf(path, sizeof path, "%s", slash ? slash : p);
            path[strcspn(path, "\n")] = 0;
            if (realpath(path, real)) snprintf(out, len, "%s", real);
            else snprintf(out, len, "%s", p);
            if (!strstr(p, "libblas.so")) break; /* a specific implementation beats the generic name */
        }
    }
    fclose(f);
}

static const char *ordering_name(int o) {
    switch (o) {
        case CHOLMOD_NATURAL: return "natural";
        case CHOLMOD_GIVEN: return "given";
        case CHOLMOD_AMD: return "amd";
        case CHOLMOD_METIS: return "metis";
        case CHOLMOD_NESDIS: return "nesdis";
        case CHOLMOD_COLAMD: return "colamd";
        case CHOLMOD_POSTORDERED: return "postordered";
        default: return "?";
    }
}

int main(int argc, char **argv) {
    run_single_threaded(argv);

    const char *matrix = NULL, *mode = "supernodal", *ordering = "amd";
    int repeat = 50;
    for (int k = 1; k < argc; ++k) {
        if (!strcmp(argv[k], "-h") || !strcmp(argv[k], "--help")) usage("help requested");
        if (k + 1 >= argc) usage("missing option value");
        const char *key = argv[k], *val = argv[++k];
        if (!strcmp(key, "--matrix")) matrix = val;
        else if (!strcmp(key, "--repeat")) repeat = atoi(val);
        else if (!strcmp(key, "--mode")) mode = val;
        else if (!strcmp(key, "--ordering")) ordering = val;
        else usage("unknown option");
    }
    if (!matrix) usage("--matrix is required");
    if (repeat < 1) usage("--repeat must be >= 1");

    cholmod_common c;
    cholmod_start(&c);
    c.print = 0;  /* quiet; errors are reported through c.status */

    if (!strcmp(mode, "supernodal")) c.supernodal = CHOLMOD_SUPERNODAL;
    else if (!strcmp(mode, "simplicial")) c.supernodal = CHOLMOD_SIMPLICIAL;
    else if (!strcmp(mode, "auto")) c.supernodal = CHOLMOD_AUTO;
    else usage("--mode must be supernodal, simplicial or auto");

    c.postorder = 1;
    if (!strcmp(ordering, "amd")) { c.nmethods = 1; c.method[0].ordering = CHOLMOD_AMD; }
    else if (!strcmp(ordering, "metis")) { c.nmethods = 1; c.method[0].ordering = CHOLMOD_METIS; }
    else if (!strcmp(ordering, "nesdis")) { c.nmethods = 1; c.method[0].ordering = CHOLMOD_NESDIS; }
    else if (!strcmp(ordering, "best")) { c.nmethods = 9; }
    else if (!strcmp(ordering, "default")) { c.nmethods = 0; }
    else usage("--ordering must be amd, metis, nesdis, best or default");

    /* ---- read (untimed) ---- */
    FILE *f = fopen(matrix, "r");
    if (!f) fail(matrix, strerror(errno));
    cholmod_sparse *A = cholmod_read_sparse(f, &c);
    fclose(f);
    if (!A) fail(matrix, "cholmod_read_sparse failed (not a real Matrix Market matrix?)");
    if (A->nrow != A->ncol) fail(matrix, "matrix is not square");
    if (A->stype == 0) fail(matrix, "matrix is not marked symmetric (expected 'coordinate real symmetric')");
    if (A->xtype != CHOLMOD_REAL) fail(matrix, "matrix is not real");

    /* ---- analyze once ---- */
    double t0 = now_seconds();
    cholmod_factor *L = cholmod_analyze(A, &c);
    double analyze_seconds = now_seconds() - t0;
    if (!L || c.status < CHOLMOD_OK) fail(matrix, "cholmod_analyze failed");
    const int selected_ordering = c.method[c.selected].ordering;
    const double flops = c.fl, lnz = c.lnz;

    /* ---- first numeric factorisation (allocates L's numeric part) ---- */
    t0 = now_seconds();
    cholmod_factorize(A, L, &c);
    double first_numeric_seconds = now_seconds() - t0;
    if (c.status != CHOLMOD_OK || L->minor < L->n) fail(matrix, "matrix is not positive definite");

    /* ---- timed numeric factorisations ---- */
    double *runs = malloc((size_t)repeat * sizeof *runs);
    for (int r = 0; r < repeat; ++r) {
        t0 = now_seconds();
        cholmod_factorize(A, L, &c);
        runs[r] = now_seconds() - t0;
        if (c.status != CHOLMOD_OK || L->minor < L->n) fail(matrix, "factorisation failed on repeat");
    }

    /* ---- sanity check (untimed): solve A x = b for b = A·1 and report the relative residual ---- */
    cholmod_dense *ones = cholmod_ones(A->nrow, 1, CHOLMOD_REAL, &c);
    cholmod_dense *b = cholmod_zeros(A->nrow, 1, CHOLMOD_REAL, &c);
    double alpha[2] = {1, 0}, beta0[2] = {0, 0}, minus1[2] = {-1, 0}, one[2] = {1, 0};
    cholmod_sdmult(A, 0, alpha, beta0, ones, b, &c);
    cholmod_dense *x = cholmod_solve(CHOLMOD_A, L, b, &c);
    cholmod_dense *res = cholmod_copy_dense(b, &c);
    cholmod_sdmult(A, 0, minus1, one, x, res, &c); /* res = b - A x */
    double rel_residual = cholmod_norm_dense(res, 0, &c) / cholmod_norm_dense(b, 0, &c);

    /* factor nnz: for a supernodal factor count the stored entries of L's supernodes (incl.
     * amalgamation zeros); for simplicial, the column counts. lnz is CHOLMOD's fill count
     * without amalgamation zeros. */
    double factor_nnz = 0;
    if (L->is_super) {
        const int *super = L->super, *pi = L->pi;
        for (size_t s = 0; s < L->nsuper; ++s) {
            double ncols = super[s + 1] - super[s], nrows = pi[s + 1] - pi[s];
            factor_nnz += ncols * nrows - ncols * (ncols - 1) / 2; /* lower trapezoid */
        }
    } else {
        const int *lnz_col = L->nz;
        for (size_t j = 0; j < L->n; ++j) factor_nnz += lnz_col[j];
    }

    /* nnz of the full symmetric matrix (both triangles), and of the stored triangle */
    const double stored_nnz = (double)cholmod_nnz(A, &c);
    const int *Ap = A->p, *Ai = A->i;
    double diag = 0;
    for (size_t j = 0; j < A->ncol; ++j)
        for (int p = Ap[j]; p < Ap[j + 1]; ++p)
            if ((size_t)Ai[p] == j) diag += 1;

    char blas[4096];
    detect_blas(blas, sizeof blas);

    printf("{\"system\":\"cholmod\",\"matrix\":");
    json_string(matrix);
    printf(",\"mode\":");
    json_string(mode);
    printf(",\"factor_kind\":\"%s\"", L->is_super ? "supernodal" : "simplicial");
    printf(",\"ordering\":");
    json_string(ordering);
    printf(",\"ordering_used\":\"%s\"", ordering_name(selected_ordering));
    printf(",\"n\":%zu,\"nnz\":%.0f,\"nnz_stored_triangle\":%.0f", A->nrow,
           2 * stored_nnz - diag, stored_nnz);
    /* cholmod_read_sparse returns symmetric matrices in upper form whichever triangle the file
     * stored, so this is CHOLMOD's internal storage, not the file's. */
    printf(",\"internal_triangle\":\"%s\"", A->stype > 0 ? "upper" : "lower");
    printf(",\"factor_nnz\":%.0f,\"factor_lnz\":%.0f,\"flops\":%.0f", factor_nnz, lnz, flops);
    printf(",\"repeat\":%d,\"numeric_seconds_runs\":[", repeat);
    for (int r = 0; r < repeat; ++r) {
        if (r) putchar(',');
        json_number(runs[r]);
    }
    printf("],\"numeric_seconds\":");
    json_number(median(runs, repeat));
    printf(",\"first_numeric_seconds\":");
    json_number(first_numeric_seconds);
    printf(",\"analyze_seconds\":");
    json_number(analyze_seconds);
    printf(",\"rel_residual\":");
    json_number(rel_residual);
    printf(",\"blas\":");
    json_string(blas);
    printf(",\"blas_threads_env\":");
    json_string(getenv("OPENBLAS_NUM_THREADS") ? getenv("OPENBLAS_NUM_THREADS") : "");
    printf(",\"cholmod_version\":\"%d.%d.%d\",\"error\":null}\n", CHOLMOD_MAIN_VERSION,
           CHOLMOD_SUB_VERSION, CHOLMOD_SUBSUB_VERSION);

    free(runs);
    cholmod_free_dense(&ones, &c);
    cholmod_free_dense(&b, &c);
    cholmod_free_dense(&x, &c);
    cholmod_free_dense(&res, &c);
    cholmod_free_factor(&L, &c);
    cholmod_free_sparse(&A, &c);
    cholmod_finish(&c);
    return 0;
}
