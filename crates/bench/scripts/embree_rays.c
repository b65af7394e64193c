/*
 * embree_rays.c -- benchmark-only reference: Embree 3 ray throughput on the
 * mesh and ray sets exported by `matflow-bench render --export DIR`.
 *
 * Embree is NOT a dependency of matflow.  `matflow-bench render` compiles
 * this file with the system C compiler when /usr/include/embree3/rtcore.h
 * exists and runs it, so matflow's BVH and Embree are measured in the same
 * run on identical rays.
 *
 * Build:
 *   cc -O3 -march=native -o /tmp/embree_rays crates/bench/scripts/embree_rays.c -lembree3 -lpthread
 *
 * Usage:
 *   embree_rays DIR [--threads N] [--runs R] [--quality medium|high] [--no-ftz] [--verbose]
 *
 * DIR must contain
 *   mesh.ply         binary little-endian PLY: vertex (float x, y, z) and
 *                    face (property list uchar int vertex_indices), triangles only
 *   primary.rays     little-endian float32 records (ox oy oz dx dy dz)
 *   incoherent.rays  same format
 *
 * Methodology (mirrors matflow's own `bench render` ray timings):
 *   - one RTCScene, RTC_SCENE_FLAG_NONE, one triangle geometry; build quality
 *     RTC_BUILD_QUALITY_MEDIUM by default (Embree's default for scenes and
 *     geometries), --quality high selects the spatial-split builder;
 *   - the build is repeated R times from the shared vertex/index buffers
 *     (no copies inside the timed region) and the median time is reported;
 *   - rays are traced one at a time (rtcIntersect1 / rtcOccluded1) with
 *     tnear = 0, tfar = +inf, unnormalised directions as stored; the
 *     incoherent set is also traced as streams of 1024 rays
 *     (rtcIntersect1M / rtcOccluded1M with RTC_INTERSECT_CONTEXT_FLAG_INCOHERENT,
 *     Embree's own route for many incoherent rays at once), beside
 *     matflow's streams;
 *   - N threads (the calling thread plus N-1 pthreads) take chunks of 1024
 *     rays from an atomic counter, like rayon's par_chunks(1024);
 *   - each ray set is timed R times, throughput = rays / wall time, and the
 *     median of the R throughputs is reported (no untimed warm-up pass,
 *     matching matflow);
 *   - FTZ/DAZ are enabled in the tracing threads as Embree recommends
 *     (--no-ftz leaves MXCSR alone); TBB's build workers keep their default.
 *
 * Output: human-readable lines on stderr, one JSON line on stdout.
 */

#define _POSIX_C_SOURCE 200809L

#include <embree3/rtcore.h>

#include <errno.h>
#include <math.h>
#include <pthread.h>
#include <stdarg.h>
#include <stdatomic.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <unistd.h>

#if defined(__x86_64__) || defined(__i386__) || defined(_M_X64)
#include <xmmintrin.h>
#define HAVE_MXCSR 1
#else
#define HAVE_MXCSR 0
#endif

#if defined(__BYTE_ORDER__) && __BYTE_ORDER__ != __ORDER_LITTLE_ENDIAN__
#error "embree_rays.c assumes a little-endian host (the input files are little-endian)"
#endif

#define CHUNK 1024
#define MAX_THREADS 1024

/* ------------------------------------------------------------------------ */
/* small helpers                                                            */

static void die(const char *fmt, ...)
{
    va_list ap;
    va_start(ap, fmt);
    fputs("embree_rays: error: ", stderr);
    vfprintf(stderr, fmt, ap);
    fputc('\n', stderr);
    va_end(ap);
    exit(1);
}

static void *xmalloc(size_t n)
{
    void *p = malloc(n ? n : 1);
    if (!p)
        die("out of memory allocating %zu bytes", n);
    return p;
}

/* 64-byte aligned allocation (cache line; more than Embree's 16-byte needs). */
static void *xmalloc_aligned(size_t n)
{
    void *p = NULL;
    int rc = posix_memalign(&p, 64, n ? n : 1);
    if (rc != 0 || !p)
        die("out of memory allocating %zu bytes", n);
    return p;
}

static double now_s(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

static int cmp_double(const void *a, const void *b)
{
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

/* Same definition as matflow's median(): mean of the middle two for even n. */
static double median(double *v, int n)
{
    if (n <= 0)
        return NAN;
    qsort(v, (size_t)n, sizeof *v, cmp_double);
    return (n % 2) ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
}

/* Reads a whole file; dies with a clear message on any failure. */
static unsigned char *read_whole_file(const char *path, size_t *len_out)
{
    FILE *f = fopen(path, "rb");
    if (!f)
        die("cannot open %s: %s", path, strerror(errno));
    if (fseeko(f, 0, SEEK_END) != 0)
        die("cannot seek in %s: %s", path, strerror(errno));
    off_t end = ftello(f);
    if (end < 0)
        die("cannot get size of %s: %s", path, strerror(errno));
    if (fseeko(f, 0, SEEK_SET) != 0)
        die("cannot seek in %s: %s", path, strerror(errno));
    size_t len = (size_t)end;
    unsigned char *buf = xmalloc(len + 1);
    size_t got = fread(buf, 1, len, f);
    if (got != len) {
        if (ferror(f))
            die("read error on %s: %s", path, strerror(errno));
        die("short read on %s: got %zu of %zu bytes", path, got, len);
    }
    fclose(f);
    buf[len] = 0;
    *len_out = len;
    return buf;
}

static char *join_path(const char *dir, const char *name)
{
    size_t a = strlen(dir), b = strlen(name);
    char *p = xmalloc(a + b + 2);
    memcpy(p, dir, a);
    size_t k = a;
    if (a > 0 && dir[a - 1] != '/')
        p[k++] = '/';
    memcpy(p + k, name, b + 1);
    return p;
}

/* ------------------------------------------------------------------------ */
/* PLY                                                                      */

typedef struct {
    size_t nverts, ntris;
    float *verts;     /* 3 * nverts floats, plus padding for Embree SSE loads */
    unsigned *index;  /* 3 * ntris */
} Mesh;

/* Splits s into whitespace-separated tokens (in place); returns count. */
static int tokenize(char *s, char **tok, int max)
{
    int n = 0;
    char *save = NULL;
    for (char *t = strtok_r(s, " \t\r", &save); t && n < max; t = strtok_r(NULL, " \t\r", &save))
        tok[n++] = t;
    return n;
}

static int is_float_type(const char *t) { return !strcmp(t, "float") || !strcmp(t, "float32"); }
static int is_uchar_type(const char *t) { return !strcmp(t, "uchar") || !strcmp(t, "uint8"); }
static int is_int_type(const char *t)
{
    return !strcmp(t, "int") || !strcmp(t, "int32") || !strcmp(t, "uint") || !strcmp(t, "uint32");
}

static size_t parse_count(const char *path, int line, const char *s)
{
    char *end = NULL;
    errno = 0;
    unsigned long long v = strtoull(s, &end, 10);
    if (errno || !end || *end || s[0] == '-' || v > (unsigned long long)UINT32_MAX)
        die("%s: header line %d: bad element count '%s'", path, line, s);
    return (size_t)v;
}

static Mesh load_ply(const char *path)
{
    size_t len;
    unsigned char *buf = read_whole_file(path, &len);

    static const char marker[] = "end_header\n";
    if (len < 4 || memcmp(buf, "ply", 3) != 0 || (buf[3] != '\n' && buf[3] != '\r'))
        die("%s: not a PLY file (missing 'ply' magic line)", path);

    /* Find the end of the header: a line that is exactly "end_header". */
    size_t hdr_end = 0;
    for (size_t i = 0; i + sizeof marker - 1 <= len && i < (1u << 20); i++) {
        if ((i == 0 || buf[i - 1] == '\n') && memcmp(buf + i, "end_header", 10) == 0) {
            size_t j = i + 10;
            if (j < len && buf[j] == '\r')
                j++;
            if (j < len && buf[j] == '\n') {
                hdr_end = j + 1;
                break;
            }
        }
    }
    if (!hdr_end)
        die("%s: PLY header has no 'end_header' line", path);

    char *hdr = xmalloc(hdr_end + 1);
    memcpy(hdr, buf, hdr_end);
    hdr[hdr_end] = 0;

    /* state: 0 = before any element, 1 = in vertex, 2 = in face */
    int state = 0, line = 0, have_format = 0, have_vertex = 0, have_face = 0;
    int nvprops = 0, nfprops = 0;
    size_t nverts = 0, ntris = 0;
    char *save = NULL;
    for (char *l = strtok_r(hdr, "\n", &save); l; l = strtok_r(NULL, "\n", &save)) {
        line++;
        char *tok[8];
        int n = tokenize(l, tok, 8);
        if (n == 0)
            continue;
        if (line == 1) {
            if (n != 1 || strcmp(tok[0], "ply"))
                die("%s: not a PLY file", path);
            continue;
        }
        if (!strcmp(tok[0], "comment") || !strcmp(tok[0], "obj_info"))
            continue;
        if (!strcmp(tok[0], "end_header"))
            break;
        if (!strcmp(tok[0], "format")) {
            if (n != 3 || strcmp(tok[1], "binary_little_endian") || strcmp(tok[2], "1.0"))
                die("%s: header line %d: only 'format binary_little_endian 1.0' is supported", path, line);
            have_format = 1;
            continue;
        }
        if (!strcmp(tok[0], "element")) {
            if (n != 3)
                die("%s: header line %d: malformed element line", path, line);
            if (!strcmp(tok[1], "vertex") && !have_vertex && !have_face) {
                nverts = parse_count(path, line, tok[2]);
                have_vertex = 1;
                state = 1;
            } else if (!strcmp(tok[1], "face") && have_vertex && !have_face) {
                ntris = parse_count(path, line, tok[2]);
                have_face = 1;
                state = 2;
            } else {
                die("%s: header line %d: unsupported element '%s' (expected exactly 'vertex' then 'face')",
                    path, line, tok[1]);
            }
            continue;
        }
        if (!strcmp(tok[0], "property")) {
            static const char *xyz[3] = {"x", "y", "z"};
            if (state == 1) {
                if (nvprops >= 3 || n != 3 || !is_float_type(tok[1]) || strcmp(tok[2], xyz[nvprops]))
                    die("%s: header line %d: unsupported vertex property (expected exactly float x, float y, float z)",
                        path, line);
                nvprops++;
            } else if (state == 2) {
                if (nfprops >= 1 || n != 5 || strcmp(tok[1], "list") || !is_uchar_type(tok[2]) ||
                    !is_int_type(tok[3]) || (strcmp(tok[4], "vertex_indices") && strcmp(tok[4], "vertex_index")))
                    die("%s: header line %d: unsupported face property (expected exactly "
                        "'property list uchar int vertex_indices')", path, line);
                nfprops++;
            } else {
                die("%s: header line %d: property before any element", path, line);
            }
            continue;
        }
        die("%s: header line %d: unsupported header keyword '%s'", path, line, tok[0]);
    }
    free(hdr);
    if (!have_format)
        die("%s: PLY header has no 'format' line", path);
    if (!have_vertex || nvprops != 3)
        die("%s: PLY header lacks 'element vertex' with float x, y, z", path);
    if (!have_face || nfprops != 1)
        die("%s: PLY header lacks 'element face' with 'property list uchar int vertex_indices'", path);
    if (nverts == 0 || ntris == 0)
        die("%s: empty mesh (%zu vertices, %zu faces)", path, nverts, ntris);

    size_t body = len - hdr_end;
    size_t need = nverts * 12 + ntris * 13;
    if (body < need)
        die("%s: truncated: body has %zu bytes, %zu vertices and %zu triangles need %zu", path, body, nverts,
            ntris, need);
    if (body > need)
        die("%s: %zu unexpected trailing bytes after %zu vertices and %zu faces (non-triangle faces?)", path,
            body - need, nverts, ntris);

    Mesh m;
    m.nverts = nverts;
    m.ntris = ntris;
    /* Embree reads the last vertex with a 16-byte load: pad by one float4. */
    m.verts = xmalloc_aligned(nverts * 12 + 16);
    memset(m.verts, 0, nverts * 12 + 16);
    memcpy(m.verts, buf + hdr_end, nverts * 12);
    for (size_t i = 0; i < 3 * nverts; i++)
        if (!isfinite(m.verts[i]))
            die("%s: vertex %zu has a non-finite coordinate", path, i / 3);

    m.index = xmalloc_aligned(ntris * 12);
    const unsigned char *p = buf + hdr_end + nverts * 12;
    for (size_t f = 0; f < ntris; f++, p += 13) {
        if (p[0] != 3)
            die("%s: face %zu has %u vertices; only triangles are supported", path, f, (unsigned)p[0]);
        int32_t idx[3];
        memcpy(idx, p + 1, 12);
        for (size_t k = 0; k < 3; k++) {
            if (idx[k] < 0 || (size_t)idx[k] >= nverts)
                die("%s: face %zu references vertex %d, mesh has %zu vertices", path, f, idx[k], nverts);
            m.index[3 * f + k] = (unsigned)idx[k];
        }
    }
    free(buf);
    return m;
}

/* ------------------------------------------------------------------------ */
/* rays                                                                     */

typedef struct {
    size_t n;
    float *r; /* 6 * n floats: ox oy oz dx dy dz */
} Rays;

static Rays load_rays(const char *path)
{
    size_t len;
    unsigned char *buf = read_whole_file(path, &len);
    if (len == 0)
        die("%s: empty ray file", path);
    if (len % 24 != 0)
        die("%s: size %zu is not a multiple of 24 bytes (6 float32 per ray); truncated?", path, len);
    Rays r;
    r.n = len / 24;
    r.r = xmalloc_aligned(len);
    memcpy(r.r, buf, len);
    free(buf);
    for (size_t i = 0; i < 6 * r.n; i++)
        if (!isfinite(r.r[i]))
            die("%s: ray %zu has a non-finite component", path, i / 6);
    return r;
}

/* ------------------------------------------------------------------------ */
/* Embree error handling                                                    */

static atomic_int g_embree_errors;

static const char *rtc_error_name(enum RTCError e)
{
    switch (e) {
    case RTC_ERROR_NONE: return "RTC_ERROR_NONE";
    case RTC_ERROR_UNKNOWN: return "RTC_ERROR_UNKNOWN";
    case RTC_ERROR_INVALID_ARGUMENT: return "RTC_ERROR_INVALID_ARGUMENT";
    case RTC_ERROR_INVALID_OPERATION: return "RTC_ERROR_INVALID_OPERATION";
    case RTC_ERROR_OUT_OF_MEMORY: return "RTC_ERROR_OUT_OF_MEMORY";
    case RTC_ERROR_UNSUPPORTED_CPU: return "RTC_ERROR_UNSUPPORTED_CPU";
    case RTC_ERROR_CANCELLED: return "RTC_ERROR_CANCELLED";
    }
    return "RTC_ERROR_?";
}

static void on_embree_error(void *user, enum RTCError code, const char *msg)
{
    (void)user;
    fprintf(stderr, "embree_rays: embree error %s: %s\n", rtc_error_name(code), msg ? msg : "(no message)");
    atomic_fetch_add(&g_embree_errors, 1);
}

static void check_embree(const char *what)
{
    if (atomic_load(&g_embree_errors) > 0)
        die("aborting after Embree error(s) during %s", what);
}

/* ------------------------------------------------------------------------ */
/* tracing                                                                  */

typedef struct {
    RTCScene scene;
    const Rays *rays;
    int occlusion;
    int stream; /* trace each chunk with one rtcIntersect1M / rtcOccluded1M call */
    atomic_size_t next_chunk;
    size_t nchunks;
} Job;

typedef struct {
    Job *job;
    size_t count; /* hits or occluded rays found by this worker */
    pthread_t tid;
    struct RTCRayHit *buf; /* a chunk of rays for the stream calls */
} Worker;

/* Embree's documented recommendation: flush-to-zero and denormals-are-zero
 * in every thread that builds or traces (Rust/matflow leaves MXCSR at its
 * default; --no-ftz reproduces that). */
static int g_ftz = 1;

/* Per-thread ray buffers of the stream calls. */
static struct RTCRayHit *g_bufs[MAX_THREADS];

static void set_ftz_daz(void)
{
#if HAVE_MXCSR
    if (g_ftz) {
        _mm_setcsr(_mm_getcsr() | 0x8040u); /* FTZ (bit 15) | DAZ (bit 6) */
    }
#endif
}

static void *worker_main(void *arg)
{
    Worker *w = arg;
    Job *job = w->job;
    set_ftz_daz();
    const float *rays = job->rays->r;
    const size_t n = job->rays->n;
    struct RTCIntersectContext ctx;
    rtcInitIntersectContext(&ctx);
    size_t count = 0;
    for (;;) {
        size_t c = atomic_fetch_add_explicit(&job->next_chunk, 1, memory_order_relaxed);
        if (c >= job->nchunks)
            break;
        size_t begin = c * CHUNK, end = begin + CHUNK < n ? begin + CHUNK : n;
        if (job->stream) {
            struct RTCIntersectContext sctx;
            rtcInitIntersectContext(&sctx);
            sctx.flags = RTC_INTERSECT_CONTEXT_FLAG_INCOHERENT;
            for (size_t i = begin; i < end; i++) {
                const float *q = rays + 6 * i;
                struct RTCRayHit *rh = &w->buf[i - begin];
                rh->ray.org_x = q[0]; rh->ray.org_y = q[1]; rh->ray.org_z = q[2];
                rh->ray.dir_x = q[3]; rh->ray.dir_y = q[4]; rh->ray.dir_z = q[5];
                rh->ray.tnear = 0.0f;
                rh->ray.tfar = INFINITY;
                rh->ray.time = 0.0f;
                rh->ray.mask = 0xFFFFFFFFu;
                rh->ray.id = (unsigned)i;
                rh->ray.flags = 0;
                rh->hit.geomID = RTC_INVALID_GEOMETRY_ID;
                rh->hit.primID = RTC_INVALID_GEOMETRY_ID;
                rh->hit.instID[0] = RTC_INVALID_GEOMETRY_ID;
            }
            unsigned m = (unsigned)(end - begin);
            if (job->occlusion) {
                /* RTCRay is the first member of RTCRayHit: a stream of rays
                 * with the RTCRayHit stride. */
                rtcOccluded1M(job->scene, &sctx, &w->buf[0].ray, m, sizeof(struct RTCRayHit));
                for (unsigned k = 0; k < m; k++)
                    count += (w->buf[k].ray.tfar < 0.0f);
            } else {
                rtcIntersect1M(job->scene, &sctx, w->buf, m, sizeof(struct RTCRayHit));
                for (unsigned k = 0; k < m; k++)
                    count += (w->buf[k].hit.geomID != RTC_INVALID_GEOMETRY_ID);
            }
            continue;
        }
        for (size_t i = begin; i < end; i++) {
            const float *q = rays + 6 * i;
            if (job->occlusion) {
                struct RTCRay ray;
                ray.org_x = q[0]; ray.org_y = q[1]; ray.org_z = q[2];
                ray.dir_x = q[3]; ray.dir_y = q[4]; ray.dir_z = q[5];
                ray.tnear = 0.0f;
                ray.tfar = INFINITY;
                ray.time = 0.0f;
                ray.mask = 0xFFFFFFFFu;
                ray.id = (unsigned)i;
                ray.flags = 0;
                rtcOccluded1(job->scene, &ctx, &ray);
                /* Embree sets tfar to -inf when an occluder is found. */
                count += (ray.tfar < 0.0f);
            } else {
                struct RTCRayHit rh;
                rh.ray.org_x = q[0]; rh.ray.org_y = q[1]; rh.ray.org_z = q[2];
                rh.ray.dir_x = q[3]; rh.ray.dir_y = q[4]; rh.ray.dir_z = q[5];
                rh.ray.tnear = 0.0f;
                rh.ray.tfar = INFINITY;
                rh.ray.time = 0.0f;
                rh.ray.mask = 0xFFFFFFFFu;
                rh.ray.id = (unsigned)i;
                rh.ray.flags = 0;
                rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
                rh.hit.primID = RTC_INVALID_GEOMETRY_ID;
                rh.hit.instID[0] = RTC_INVALID_GEOMETRY_ID;
                rtcIntersect1(job->scene, &ctx, &rh);
                count += (rh.hit.geomID != RTC_INVALID_GEOMETRY_ID);
            }
        }
    }
    w->count = count;
    return NULL;
}

/* One timed pass over all rays with nthreads threads; returns seconds. */
static double trace_once(RTCScene scene, const Rays *rays, int occlusion, int stream, int nthreads,
                         size_t *count_out)
{
    Job job;
    job.scene = scene;
    job.rays = rays;
    job.occlusion = occlusion;
    job.stream = stream;
    job.nchunks = (rays->n + CHUNK - 1) / CHUNK;
    atomic_init(&job.next_chunk, 0);

    Worker w[MAX_THREADS];
    for (int t = 0; t < nthreads; t++) {
        w[t].job = &job;
        w[t].count = 0;
        w[t].buf = g_bufs[t];
    }
    double t0 = now_s();
    for (int t = 1; t < nthreads; t++) {
        int rc = pthread_create(&w[t].tid, NULL, worker_main, &w[t]);
        if (rc != 0)
            die("pthread_create failed: %s", strerror(rc));
    }
    worker_main(&w[0]); /* the calling thread is worker 0 */
    for (int t = 1; t < nthreads; t++) {
        int rc = pthread_join(w[t].tid, NULL);
        if (rc != 0)
            die("pthread_join failed: %s", strerror(rc));
    }
    double dt = now_s() - t0;
    size_t total = 0;
    for (int t = 0; t < nthreads; t++)
        total += w[t].count;
    *count_out = total;
    return dt;
}

/* Times a ray set `runs` times; returns median Mrays/s, stores the count. */
static double bench_rays(const char *label, RTCScene scene, const Rays *rays, int occlusion, int stream,
                         int nthreads, int runs, size_t *count_out)
{
    double *mr = xmalloc(sizeof(double) * (size_t)runs);
    size_t count = 0;
    for (int r = 0; r < runs; r++) {
        size_t c = 0;
        double dt = trace_once(scene, rays, occlusion, stream, nthreads, &c);
        check_embree(label);
        if (r > 0 && c != count)
            die("%s: hit count changed between runs (%zu vs %zu)", label, count, c);
        count = c;
        mr[r] = (double)rays->n / dt / 1e6;
    }
    double med = median(mr, runs);
    free(mr);
    fprintf(stderr, "  %-24s %8.2f Mrays/s (%zu rays, %zu %s)\n", label, med, rays->n, count,
            occlusion ? "occluded" : "hits");
    *count_out = count;
    return med;
}

/* ------------------------------------------------------------------------ */
/* main                                                                     */

static void usage(void)
{
    fprintf(stderr,
            "usage: embree_rays DIR [--threads N] [--runs R] [--quality medium|high] [--no-ftz] [--verbose]\n"
            "  DIR holds mesh.ply, primary.rays, incoherent.rays "
            "(from `matflow-bench render --export DIR`)\n");
    exit(2);
}

static long parse_pos_int(const char *opt, const char *s, long max)
{
    char *end = NULL;
    errno = 0;
    long v = strtol(s, &end, 10);
    if (errno || !end || *end || v < 1 || v > max) {
        fprintf(stderr, "embree_rays: %s expects an integer in 1..%ld, got '%s'\n", opt, max, s);
        exit(2);
    }
    return v;
}

int main(int argc, char **argv)
{
    const char *dir = NULL;
    int nthreads = 0, runs = 3, verbose = 0;
    enum RTCBuildQuality quality = RTC_BUILD_QUALITY_MEDIUM;
    for (int i = 1; i < argc; i++) {
        const char *a = argv[i];
        if (!strcmp(a, "--threads") && i + 1 < argc)
            nthreads = (int)parse_pos_int(a, argv[++i], MAX_THREADS);
        else if (!strcmp(a, "--runs") && i + 1 < argc)
            runs = (int)parse_pos_int(a, argv[++i], 100000);
        else if (!strcmp(a, "--quality") && i + 1 < argc) {
            const char *q = argv[++i];
            if (!strcmp(q, "medium"))
                quality = RTC_BUILD_QUALITY_MEDIUM;
            else if (!strcmp(q, "high"))
                quality = RTC_BUILD_QUALITY_HIGH;
            else {
                fprintf(stderr, "embree_rays: --quality expects 'medium' or 'high', got '%s'\n", q);
                exit(2);
            }
        } else if (!strcmp(a, "--verbose"))
            verbose = 1;
        else if (!strcmp(a, "--no-ftz"))
            g_ftz = 0;
        else if (!strcmp(a, "-h") || !strcmp(a, "--help"))
            usage();
        else if (a[0] == '-' ) {
            fprintf(stderr, "embree_rays: unknown or incomplete option '%s'\n", a);
            usage();
        } else if (!dir)
            dir = a;
        else {
            fprintf(stderr, "embree_rays: unexpected argument '%s'\n", a);
            usage();
        }
    }
    if (!dir)
        usage();
    if (nthreads == 0) {
        long n = sysconf(_SC_NPROCESSORS_ONLN);
        nthreads = n < 1 ? 1 : (n > MAX_THREADS ? MAX_THREADS : (int)n);
    }
    const char *quality_name = quality == RTC_BUILD_QUALITY_HIGH ? "high" : "medium";

    /* Inputs. */
    char *mesh_path = join_path(dir, "mesh.ply");
    char *prim_path = join_path(dir, "primary.rays");
    char *inco_path = join_path(dir, "incoherent.rays");
    Mesh mesh = load_ply(mesh_path);
    Rays primary = load_rays(prim_path);
    Rays incoherent = load_rays(inco_path);

    set_ftz_daz(); /* the main thread builds (with TBB workers) and traces */

    /* Device: build threads limited to the same count as the tracing threads. */
    char config[128];
    snprintf(config, sizeof config, "threads=%d%s", nthreads, verbose ? ",verbose=1" : "");
    RTCDevice device = rtcNewDevice(config);
    if (!device) {
        enum RTCError e = rtcGetDeviceError(NULL);
        die("rtcNewDevice(\"%s\") failed: %s", config, rtc_error_name(e));
    }
    rtcSetDeviceErrorFunction(device, on_embree_error, NULL);
    char version[64];
    ssize_t vmaj = rtcGetDeviceProperty(device, RTC_DEVICE_PROPERTY_VERSION_MAJOR);
    ssize_t vmin = rtcGetDeviceProperty(device, RTC_DEVICE_PROPERTY_VERSION_MINOR);
    ssize_t vpat = rtcGetDeviceProperty(device, RTC_DEVICE_PROPERTY_VERSION_PATCH);
    ssize_t vnum = rtcGetDeviceProperty(device, RTC_DEVICE_PROPERTY_VERSION);
    snprintf(version, sizeof version, "%zd.%zd.%zd", vmaj, vmin, vpat);
    check_embree("device setup");
    if (vnum != vmaj * 10000 + vmin * 100 + vpat)
        fprintf(stderr, "embree_rays: warning: RTC_DEVICE_PROPERTY_VERSION %zd disagrees with %s\n", vnum, version);

    fprintf(stderr,
            "embree_rays: Embree %s (headers %s), %zu vertices, %zu triangles, %d thread(s), %d run(s), "
            "build quality %s, FTZ/DAZ %s, medians\n",
            version, RTC_VERSION_STRING, mesh.nverts, mesh.ntris, nthreads, runs, quality_name,
            (g_ftz && HAVE_MXCSR) ? "on" : "off");

    /* Build, `runs` times, from shared buffers; keep the last scene. */
    RTCScene scene = NULL;
    double *bt = xmalloc(sizeof(double) * (size_t)runs);
    for (int r = 0; r < runs; r++) {
        if (scene)
            rtcReleaseScene(scene);
        double t0 = now_s();
        scene = rtcNewScene(device);
        rtcSetSceneFlags(scene, RTC_SCENE_FLAG_NONE);
        rtcSetSceneBuildQuality(scene, quality);
        RTCGeometry geom = rtcNewGeometry(device, RTC_GEOMETRY_TYPE_TRIANGLE);
        rtcSetGeometryBuildQuality(geom, quality);
        rtcSetSharedGeometryBuffer(geom, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3, mesh.verts, 0,
                                   3 * sizeof(float), mesh.nverts);
        rtcSetSharedGeometryBuffer(geom, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3, mesh.index, 0,
                                   3 * sizeof(unsigned), mesh.ntris);
        rtcCommitGeometry(geom);
        rtcAttachGeometry(scene, geom);
        rtcReleaseGeometry(geom);
        rtcCommitScene(scene);
        bt[r] = now_s() - t0;
        check_embree("scene build");
    }
    double build_ms = median(bt, runs) * 1e3;
    free(bt);
    struct RTCBounds b;
    rtcGetSceneBounds(scene, &b);
    check_embree("scene bounds");
    fprintf(stderr, "  %-24s %8.1f ms (bounds [%g %g %g] .. [%g %g %g])\n", "BVH build", build_ms, b.lower_x,
            b.lower_y, b.lower_z, b.upper_x, b.upper_y, b.upper_z);

    for (int t = 0; t < nthreads; t++)
        g_bufs[t] = xmalloc(sizeof(struct RTCRayHit) * CHUNK);
    size_t prim_hits, prim_occl, inco_hits, inco_occl, s_hits, s_occl;
    double prim_hit_mr = bench_rays("primary closest-hit", scene, &primary, 0, 0, nthreads, runs, &prim_hits);
    double prim_occl_mr = bench_rays("primary occlusion", scene, &primary, 1, 0, nthreads, runs, &prim_occl);
    double inco_hit_mr = bench_rays("incoherent closest-hit", scene, &incoherent, 0, 0, nthreads, runs, &inco_hits);
    double inco_occl_mr = bench_rays("incoherent occlusion", scene, &incoherent, 1, 0, nthreads, runs, &inco_occl);
    double s_hit_mr = bench_rays("incoherent hit, 1M", scene, &incoherent, 0, 1, nthreads, runs, &s_hits);
    double s_occl_mr = bench_rays("incoherent occl., 1M", scene, &incoherent, 1, 1, nthreads, runs, &s_occl);
    if (s_hits != inco_hits || s_occl != inco_occl)
        die("streams found %zu hits and %zu occluded, single rays %zu and %zu", s_hits, s_occl, inco_hits,
            inco_occl);
    for (int t = 0; t < nthreads; t++)
        free(g_bufs[t]);

    if (prim_occl != prim_hits || inco_occl != inco_hits)
        fprintf(stderr,
                "embree_rays: note: occlusion and closest-hit counts differ (primary %zu vs %zu, "
                "incoherent %zu vs %zu)\n",
                prim_occl, prim_hits, inco_occl, inco_hits);

    printf("{\"embree\": \"%s\", \"threads\": %d, \"runs\": %d, \"build_quality\": \"%s\", "
           "\"ftz_daz\": %s, \"triangles\": %zu, \"build_ms\": %.2f, "
           "\"primary_hit_mrays\": %.3f, \"primary_occl_mrays\": %.3f, "
           "\"incoherent_hit_mrays\": %.3f, \"incoherent_occl_mrays\": %.3f, "
           "\"incoherent_hit_stream_mrays\": %.3f, \"incoherent_occl_stream_mrays\": %.3f, "
           "\"primary_rays\": %zu, \"incoherent_rays\": %zu, "
           "\"primary_hits\": %zu, \"primary_occluded\": %zu, "
           "\"incoherent_hits\": %zu, \"incoherent_occluded\": %zu}\n",
           version, nthreads, runs, quality_name, (g_ftz && HAVE_MXCSR) ? "true" : "false", mesh.ntris, build_ms, prim_hit_mr, prim_occl_mr, inco_hit_mr,
           inco_occl_mr, s_hit_mr, s_occl_mr, primary.n, incoherent.n, prim_hits, prim_occl, inco_hits, inco_occl);
    if (fflush(stdout) != 0)
        die("writing to stdout failed: %s", strerror(errno));

    rtcReleaseScene(scene);
    rtcReleaseDevice(device);
    free(mesh.verts);
    free(mesh.index);
    free(primary.r);
    free(incoherent.r);
    free(mesh_path);
    free(prim_path);
    free(inco_path);
    return 0;
}
