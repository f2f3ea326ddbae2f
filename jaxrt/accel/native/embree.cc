// Closest-hit and any-hit ray queries through Embree 3 as an XLA FFI custom call (see
// jaxrt/accel/traverse_embree.py).
//
// Embree (Wald et al., "Embree: A Kernel Framework for Efficient CPU Ray Tracing", SIGGRAPH 2014)
// builds its own wide BVH (4 or 8 children per node) over the triangles and traverses ray packets
// with SIMD instructions chosen at run time for the CPU it runs on; jaxrt's own kernel
// (traverse.cc) traces one ray at a time through a binary tree.
//
// The scene. The triangles come in as jaxrt's (F, 9) leaf-order table, so Embree's primID is the
// same leaf-order index as the native kernel's `best`, and Embree's (u, v) have jaxrt's meaning: the
// hit point is (1-u-v) v0 + u v1 + v v2. Embree's tree is built once per distinct triangle table and
// kept (a few per process): every call hashes the table's bytes (one pass over memory, spread over
// the threads: ~1.7 ms for the 871k-triangle dragon's 31 MB on two loaded cores, 3-4 ms on one) and
// reuses the scene built for an identical table, so a frame
// never rebuilds it and a changed mesh never reuses a stale one. RTC_SCENE_FLAG_ROBUST selects
// Embree's Pluecker triangle test, watertight at edges (a ray through an edge shared by two triangles
// hits one of them; without the flag ~10 % of such rays slip through) but not exactly at vertices:
// a ray through a vertex can pass between the triangles of its fan when their edge functions'
// rounding noise has one sign (traverse.cc's exact signs of Woop et al. 2013 cannot).
//
// Ties and ulps. Embree's triangle test rounds differently from traverse.cc's, so of two triangles at
// the same distance to within an ulp either may be returned, and it decides the ends of
// [tmin, tmax] with its own float32 t (tnear < t <= tfar; tnear is set one float below tmin, and
// at least 0: a hit at exactly t = 0 does not count). t, u, v
// of the chosen triangle are recomputed in double (traverse.cc does so for t), so the reported hits
// agree to ~1e-7 relative whichever kernel traced the ray; on request the hit point and the unit
// geometric normal too (`Finish`), so that shading need not gather the corners again.
//
// Direct light (`Direct`): the closest hits and, per packet, the hits' shadow rays to point lights
// (`Shadows16`), so that a Whitted frame of depth 1 is one call (BENCHMARKS.md, "Direct-light frames
// on the CPU: shadow rays in the traversal call").
//
// Threads: chunks of consecutive rays (coherent image tiles) handed out by an atomic counter to the
// caller and to tasks on XLA's intra-op thread pool, as in traverse.cc. Each chunk is traced in
// packets of 16 rays (rtcIntersect16 / rtcOccluded16); Embree picks its kernels for the instruction
// set of the CPU it runs on (this file needs no -march).

#include <embree3/rtcore.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <condition_variable>
#include <cstdint>
#include <cstring>
#include <list>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

namespace {

// ---------------------------------------------------------------------------------------------
// Scenes, built once per distinct triangle table.

struct Scene {
  RTCScene scene = nullptr;
  uint64_t hash = 0;
  int64_t nf = 0;
  const float* corners = nullptr;  // Embree's copy of the table (owned by the geometry the scene holds)
  ~Scene() {
    if (scene) rtcReleaseScene(scene);
  }
};

std::mutex g_mu;
RTCDevice g_device = nullptr;
std::mutex g_error_mu;  // Embree may report from its build threads
std::string g_error;
std::list<std::shared_ptr<Scene>> g_scenes;  // most recently used first
constexpr size_t kMaxScenes = 4;             // a fit or a notebook alternates between a few meshes

void OnError(void*, RTCError code, const char* str) {
  std::lock_guard<std::mutex> lock(g_error_mu);
  g_error = std::string("Embree error ") + std::to_string(static_cast<int>(code)) + ": " + (str ? str : "");
}

std::string TakeError() {
  std::lock_guard<std::mutex> lock(g_error_mu);
  std::string e;
  e.swap(g_error);
  return e;
}

// 64-bit hash of the table's bytes: four independent multiply-xor lanes over 8-byte words (the
// loop is memory bound), then mixed (the finaliser of SplitMix64).
uint64_t Hash(const void* data, size_t bytes) {
  const unsigned char* p = static_cast<const unsigned char*>(data);
  uint64_t h[4] = {0x9E3779B97F4A7C15ull, 0xC2B2AE3D27D4EB4Full, 0x165667B19E3779F9ull, 0x27D4EB2F165667C5ull};
  constexpr uint64_t kMul = 0xff51afd7ed558ccdull;
  size_t i = 0;
  for (; i + 32 <= bytes; i += 32) {
    uint64_t w[4];
    std::memcpy(w, p + i, 32);
    for (int k = 0; k < 4; ++k) h[k] = (h[k] ^ w[k]) * kMul;
  }
  uint64_t tail = 0;
  std::memcpy(&tail, p + i, bytes - i < 8 ? bytes - i : 8);  // the table is float32: 4-byte multiples
  for (size_t j = i + 8; j < bytes; j += 8) {
    uint64_t w = 0;
    std::memcpy(&w, p + j, std::min<size_t>(8, bytes - j));
    tail = (tail ^ w) * kMul;
  }
  uint64_t x = h[0] ^ (h[1] << 1 | h[1] >> 63) ^ (h[2] << 2 | h[2] >> 62) ^ (h[3] << 3 | h[3] >> 61) ^ tail ^ bytes;
  x ^= x >> 30;
  x *= 0xbf58476d1ce4e5b9ull;
  x ^= x >> 27;
  x *= 0x94d049bb133111ebull;
  x ^= x >> 31;
  return x;
}

// Hash of the table in pieces of 4 MB (each piece's Hash, then the pieces' hashes hashed; the same
// value however many threads share the work), pieces taken from a counter by the caller and by
// tasks on the pool: the table is read once per call, so on a large mesh this pass is worth
// spreading over the cores.
struct HashJob {
  const unsigned char* data;
  size_t bytes, n;
  std::vector<uint64_t> out;
  std::atomic<size_t> next{0};
  std::atomic<size_t> done{0};
  std::mutex mu;
  std::condition_variable cv;
};

constexpr size_t kPiece = size_t{4} << 20;

void HashPieces(HashJob& H) {
  for (;;) {
    const size_t k = H.next.fetch_add(1);
    if (k >= H.n) return;
    const size_t s = k * kPiece, e = std::min(H.bytes, s + kPiece);
    H.out[k] = Hash(H.data + s, e - s);
    if (H.done.fetch_add(1) + 1 == H.n) {
      std::lock_guard<std::mutex> lock(H.mu);
      H.cv.notify_all();
    }
  }
}

uint64_t TableHash(ffi::ThreadPool& pool, bool use_pool, const float* tri, int64_t nf) {
  const size_t bytes = static_cast<size_t>(nf) * 9 * sizeof(float);
  const size_t n = (bytes + kPiece - 1) / kPiece;
  if (n <= 1) return Hash(tri, bytes);
  auto H = std::make_shared<HashJob>();
  H->data = reinterpret_cast<const unsigned char*>(tri);
  H->bytes = bytes;
  H->n = n;
  H->out.assign(n, 0);
  const int64_t helpers = use_pool ? std::min<int64_t>(pool.num_threads(), static_cast<int64_t>(n)) - 1 : 0;
  // a task that starts after the pieces are gone returns at once; the caller waits for every piece
  for (int64_t k = 0; k < helpers; ++k) pool.Schedule([H] { HashPieces(*H); });
  HashPieces(*H);
  {
    std::unique_lock<std::mutex> lock(H->mu);
    H->cv.wait(lock, [&] { return H->done.load() == H->n; });
  }
  return Hash(H->out.data(), n * sizeof(uint64_t)) ^ bytes;
}

// The scene of a table with hash h (built now unless an identical table's is kept); nullptr and
// `err` set on failure.
std::shared_ptr<Scene> GetScene(const float* tri, int64_t nf, uint64_t h, int quality, std::string* err) {
  std::lock_guard<std::mutex> lock(g_mu);
  for (auto it = g_scenes.begin(); it != g_scenes.end(); ++it) {
    if ((*it)->hash == h && (*it)->nf == nf) {
      auto s = *it;
      g_scenes.erase(it);
      g_scenes.push_front(s);
      return s;
    }
  }
  if (!g_device) {
    g_device = rtcNewDevice("verbose=0");
    if (!g_device) {
      *err = "rtcNewDevice failed (error " + std::to_string(static_cast<int>(rtcGetDeviceError(nullptr))) + ")";
      return nullptr;
    }
    rtcSetDeviceErrorFunction(g_device, OnError, nullptr);
  }
  TakeError();  // an earlier, unrelated report
  auto s = std::make_shared<Scene>();
  s->hash = h;
  s->nf = nf;
  s->scene = rtcNewScene(g_device);
  rtcSetSceneFlags(s->scene, RTC_SCENE_FLAG_ROBUST);
  rtcSetSceneBuildQuality(s->scene, static_cast<RTCBuildQuality>(quality));
  RTCGeometry g = rtcNewGeometry(g_device, RTC_GEOMETRY_TYPE_TRIANGLE);
  // Embree copies the corners (its buffers are padded for its 16-byte loads); the table's memory
  // belongs to XLA and may be reused after this call.
  float* v = static_cast<float*>(
      rtcSetNewGeometryBuffer(g, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3, 3 * sizeof(float), 3 * nf));
  unsigned* idx = static_cast<unsigned*>(
      rtcSetNewGeometryBuffer(g, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3, 3 * sizeof(unsigned), nf));
  if (!v || !idx) {
    rtcReleaseGeometry(g);
    *err = "could not allocate Embree buffers for " + std::to_string(nf) + " triangles (" + TakeError() + ")";
    return nullptr;
  }
  std::memcpy(v, tri, static_cast<size_t>(nf) * 9 * sizeof(float));
  s->corners = v;
  for (int64_t k = 0; k < 3 * nf; ++k) idx[k] = static_cast<unsigned>(k);
  rtcCommitGeometry(g);
  rtcAttachGeometryByID(s->scene, g, 0);
  rtcReleaseGeometry(g);
  rtcCommitScene(s->scene);
  std::string e = TakeError();
  if (!e.empty()) {
    *err = e;
    return nullptr;
  }
  g_scenes.push_front(s);
  if (g_scenes.size() > kMaxScenes) g_scenes.pop_back();  // a call still tracing it holds a reference
  return s;
}

// ---------------------------------------------------------------------------------------------
// Tracing.

struct Job {
  const float* o;
  const float* d;
  const float* tmin;
  const float* tmax;
  const float* tri;
  int64_t n;
  bool any_hit, refine, points;
  int64_t coherent;  // 0: incoherent, 1: coherent, 2: per packet (see Packet16)
  int64_t packet;
  RTCScene scene;
  float* t;
  int32_t* best;
  float* u;
  float* v;
  float* p;   // (n, 3) hit points, or null (points off)
  float* ng;  // (n, 3) unit geometric normals, or null
  // Shadow rays of the direct-light call (`Direct`): nl point lights at `lights` (nl, 3), and per
  // (ray, light) whether the segment from the hit to the light is blocked; nl = 0 otherwise.
  const float* lights = nullptr;
  int64_t nl = 0;
  bool* occ = nullptr;  // (n, nl)
  int64_t chunk;
  std::atomic<int64_t> next{0};
  std::atomic<int64_t> done{0};
  std::mutex mu;
  std::condition_variable cv;
};

// The closest hits of one packet (at most 16), finished in double. With `refine`: t, u, v of each
// ray's line through the plane of its triangle: differences of floats and their products are exact
// or nearly so in double, so the float32 test's errors go (traverse.cc's RefineT does the same for
// t; Embree's float32 (u, v) stray by up to ~1e-4 of the triangle on rays nearly parallel to it).
// u, v solve q = u e1 + v e2 for the hit point q relative to v0: u = (q x e2).n / n.n,
// v = (e1 x q).n / n.n with n = e1 x e2, clamped onto the triangle (the hit is on it up to
// rounding). Embree's t is kept where the double t is not finite or strays by more than 1 %, its
// (u, v) also where the double ones are not finite. With `points`: the hit point and the unit
// geometric normal at the (double) barycentrics, rounded once: p = v0 + u e1 + v e2 (the
// barycentric point, on the triangle, as `jaxrt.shading.surface.make_surface` computes it in float32
// from the corners: a few ulps apart), ng = n / |n| (the winding's normal; 0 for a degenerate
// triangle, as `surface.normalize` gives). Returned with the hit, the shading code needs neither the
// corners' gathers nor the passes that recompute p from them (BENCHMARKS.md, "Direct-light frames
// on the CPU").
//
// Every lane is loaded first and then computed by loops over the lanes without branches: the
// triangles' cache misses overlap, and the compiler vectorises the loops (clones for AVX-512 and
// AVX2, chosen when the library is loaded; IEEE arithmetic without contraction, so every clone
// gives the same bits; traverse_embree.FLAGS lets the compiler make the quotients unconditionally).
// One hit at a time, the refinement took a quarter of a dragon camera-ray call.
struct Hits {
  int m = 0;  // lanes in use
  int64_t ray[16];
  int32_t tri[16];
  float t[16], u[16], v[16];
};

__attribute__((target_clones("avx512f", "avx2", "default"))) void Finish(const Job& J, Hits& H) {
  const int m = H.m;
  const bool refine = J.refine;
  alignas(64) double T[9][16], o[3][16], d[3][16];
  for (int k = 0; k < m; ++k) {
    const float* tk = J.tri + 9 * static_cast<int64_t>(H.tri[k]);
    for (int c = 0; c < 9; ++c) T[c][k] = tk[c];
    for (int c = 0; c < 3; ++c) {
      o[c][k] = J.o[3 * H.ray[k] + c];
      d[c][k] = J.d[3 * H.ray[k] + c];
    }
  }
  alignas(64) double ud[16], vd[16], n[3][16], nn[16], e1[3][16], e2[3][16];
  for (int k = 0; k < m; ++k) {
    e1[0][k] = T[3][k] - T[0][k];
    e1[1][k] = T[4][k] - T[1][k];
    e1[2][k] = T[5][k] - T[2][k];
    e2[0][k] = T[6][k] - T[0][k];
    e2[1][k] = T[7][k] - T[1][k];
    e2[2][k] = T[8][k] - T[2][k];
    const double a[3] = {T[0][k] - o[0][k], T[1][k] - o[1][k], T[2][k] - o[2][k]};
    n[0][k] = e1[1][k] * e2[2][k] - e1[2][k] * e2[1][k];
    n[1][k] = e1[2][k] * e2[0][k] - e1[0][k] * e2[2][k];
    n[2][k] = e1[0][k] * e2[1][k] - e1[1][k] * e2[0][k];
    const double num = n[0][k] * a[0] + n[1][k] * a[1] + n[2][k] * a[2];
    const double den = n[0][k] * d[0][k] + n[1][k] * d[1][k] + n[2][k] * d[2][k];
    nn[k] = n[0][k] * n[0][k] + n[1][k] * n[1][k] + n[2][k] * n[2][k];
    const double td = num / den;
    const float t32 = H.t[k];
    const float t = static_cast<float>(td);
    // (fabs(x) < inf is false for NaN and infinities: std::isfinite without a branch)
    // (& rather than &&, and both quotients below made: no branches in the loop)
    const bool ok = refine & (den != 0) & (nn[k] > 0) & (std::fabs(t) < INFINITY) &
                    (std::fabs(t - t32) <= 1e-2f * std::fabs(t32) + 1e-30f);
    const double q[3] = {td * d[0][k] - a[0], td * d[1][k] - a[1], td * d[2][k] - a[2]};
    const double qe2[3] = {q[1] * e2[2][k] - q[2] * e2[1][k], q[2] * e2[0][k] - q[0] * e2[2][k],
                           q[0] * e2[1][k] - q[1] * e2[0][k]};
    const double e1q[3] = {e1[1][k] * q[2] - e1[2][k] * q[1], e1[2][k] * q[0] - e1[0][k] * q[2],
                           e1[0][k] * q[1] - e1[1][k] * q[0]};
    double u = (qe2[0] * n[0][k] + qe2[1] * n[1][k] + qe2[2] * n[2][k]) / nn[k];
    double v = (e1q[0] * n[0][k] + e1q[1] * n[1][k] + e1q[2] * n[2][k]) / nn[k];
    const bool ok_uv = ok & (std::fabs(u) < INFINITY) & (std::fabs(v) < INFINITY);
    u = std::max(u, 0.0);
    v = std::max(v, 0.0);
    const double sum = u + v;
    const bool over = sum > 1.0;
    const double us = u / sum, vs = v / sum;
    u = over ? us : u;
    v = over ? vs : v;
    H.t[k] = ok ? t : t32;
    ud[k] = ok_uv ? u : static_cast<double>(H.u[k]);
    vd[k] = ok_uv ? v : static_cast<double>(H.v[k]);
    H.u[k] = static_cast<float>(ud[k]);
    H.v[k] = static_cast<float>(vd[k]);
  }
  if (!J.points) return;
  alignas(64) float p[3][16], g[3][16];
  for (int k = 0; k < m; ++k) {
    const double r = 1.0 / std::sqrt(nn[k]);
    const double s = nn[k] > 1e-30 ? r : 0.0;
    p[0][k] = static_cast<float>(T[0][k] + ud[k] * e1[0][k] + vd[k] * e2[0][k]);
    p[1][k] = static_cast<float>(T[1][k] + ud[k] * e1[1][k] + vd[k] * e2[1][k]);
    p[2][k] = static_cast<float>(T[2][k] + ud[k] * e1[2][k] + vd[k] * e2[2][k]);
    g[0][k] = static_cast<float>(n[0][k] * s);
    g[1][k] = static_cast<float>(n[1][k] * s);
    g[2][k] = static_cast<float>(n[2][k] * s);
  }
  for (int k = 0; k < m; ++k) {
    for (int c = 0; c < 3; ++c) {
      J.p[3 * H.ray[k] + c] = p[c][k];
      J.ng[3 * H.ray[k] + c] = g[c][k];
    }
  }
}

// Writes the finished hits of H to the outputs.
inline void Store(const Job& J, Hits& H) {
  if (J.refine || J.points) Finish(J, H);
  for (int k = 0; k < H.m; ++k) {
    const int64_t i = H.ray[k];
    J.t[i] = H.t[k];
    J.best[i] = H.tri[k];
    J.u[i] = H.u[k];
    J.v[i] = H.v[k];
  }
}

inline void NoPoint(const Job& J, int64_t i) {
  if (!J.points) return;
  for (int k = 0; k < 3; ++k) J.p[3 * i + k] = J.ng[3 * i + k] = 0.0f;
}

// Embree's rays must be finite with tnear <= tfar (NaN or inverted intervals are jaxrt's inactive
// slots): the others are misses without being traced.
inline bool Valid(const Job& J, int64_t i) {
  const float* o = J.o + 3 * i;
  const float* d = J.d + 3 * i;
  const float lo = J.tmin[i], hi = J.tmax[i];
  const bool finite = std::isfinite(o[0]) && std::isfinite(o[1]) && std::isfinite(o[2]) && std::isfinite(d[0]) &&
                      std::isfinite(d[1]) && std::isfinite(d[2]) && std::isfinite(lo) && !std::isnan(hi);
  return finite && lo <= hi && (d[0] != 0.0f || d[1] != 0.0f || d[2] != 0.0f);
}

// Embree counts t > tnear: start the interval one float below tmin so that t == tmin counts too.
inline float Below(float x) { return std::nextafter(x, -INFINITY); }

inline void Miss(const Job& J, int64_t i) {
  J.t[i] = J.tmax[i];
  J.best[i] = -1;
  J.u[i] = 0.0f;
  J.v[i] = 0.0f;
  NoPoint(J, i);
}

// Octant coherence of a packet (`coherent` 2): Embree's coherent mode traverses the packet as one
// (fast where its rays take the same path: camera tiles, shadow rays to one light); its incoherent
// mode splits it into single rays as they diverge (bounced rays of a path tracer). Coherent here
// when the packet's valid rays share a direction octant.
inline void PacketFlags(RTCIntersectContext* ctx, const int* valid, const float* dx, const float* dy,
                        const float* dz) {
  unsigned all = 0, any = 0;
  bool first = true;
  for (int k = 0; k < 16; ++k) {
    if (!valid[k]) continue;
    const unsigned oct = (std::signbit(dx[k]) ? 1u : 0u) | (std::signbit(dy[k]) ? 2u : 0u) |
                         (std::signbit(dz[k]) ? 4u : 0u);
    all = first ? oct : all;
    any |= oct != all;
    first = false;
  }
  ctx->flags = any ? RTC_INTERSECT_CONTEXT_FLAG_INCOHERENT : RTC_INTERSECT_CONTEXT_FLAG_COHERENT;
}

// The shadow rays of the closest hits [s, e) just stored (their p and ng are in J.p, J.ng), one
// packet per light, traced while the packet's hits are in cache. The rays are the ones the Whitted
// trace loop makes in float32 (jaxrt/integrators/whitted.py, `shadow_segments`), operation for
// operation, so that the same segments are tested:
//   ng' = ng flipped towards the ray's origin (ng if d.ng <= 0), eps = 2^-16 (1 + max_k |p_k|),
//   delta = light - p, d2 = delta.delta, dist = sqrt(d2) (0 and wi = 0 where d2 <= 1e-20),
//   wi = delta / dist, lit = wi.ng' > 0, so = p + ng' eps, smax = dist - 2 eps (lit only),
// traced from the light's end (`bvh.occluded(from_end=True)`): origin so + smax wi, direction -wi,
// [0, smax]. occ is false where the hit is missed or not lit (the caller ANDs its own `lit`).
void Shadows16(const Job& J, RTCIntersectContext* ctx, int64_t s, int64_t e) {
  alignas(64) int valid[16];
  alignas(64) RTCRay16 r;
  for (int64_t l = 0; l < J.nl; ++l) {
    const float* L = J.lights + 3 * l;
    bool any = false;
    for (int k = 0; k < 16; ++k) {
      const int64_t i = s + k;
      bool ok = i < e && J.best[i >= e ? s : i] >= 0;
      const int64_t j = i < e ? i : s;
      const float* p = J.p + 3 * j;
      const float* n = J.ng + 3 * j;
      const float* d = J.d + 3 * j;
      const float dn = d[0] * n[0] + d[1] * n[1] + d[2] * n[2];
      const float sg = dn > 0.0f ? -1.0f : 1.0f;
      const float g[3] = {n[0] * sg, n[1] * sg, n[2] * sg};
      const float a = std::max(std::max(std::fabs(p[0]), std::fabs(p[1])), std::fabs(p[2]));
      const float eps = 1.52587890625e-05f * (1.0f + a);  // 2^-16
      const float dl[3] = {L[0] - p[0], L[1] - p[1], L[2] - p[2]};
      const float d2 = dl[0] * dl[0] + dl[1] * dl[1] + dl[2] * dl[2];
      const bool safe = d2 > 1e-20f;
      const float dist = std::sqrt(safe ? d2 : 1.0f);
      const float wi[3] = {safe ? dl[0] / dist : 0.0f, safe ? dl[1] / dist : 0.0f, safe ? dl[2] / dist : 0.0f};
      const float dsafe = safe ? dist : 0.0f;
      ok = ok && (wi[0] * g[0] + wi[1] * g[1] + wi[2] * g[2]) > 0.0f;
      const float so[3] = {p[0] + g[0] * eps, p[1] + g[1] * eps, p[2] + g[2] * eps};
      const float smax = dsafe - 2.0f * eps;
      const float org[3] = {so[0] + smax * wi[0], so[1] + smax * wi[1], so[2] + smax * wi[2]};
      // as `Valid`: finite, 0 <= smax, a direction
      ok = ok && std::isfinite(org[0]) && std::isfinite(org[1]) && std::isfinite(org[2]) && std::isfinite(smax) &&
           smax >= 0.0f && (wi[0] != 0.0f || wi[1] != 0.0f || wi[2] != 0.0f);
      valid[k] = ok ? -1 : 0;
      any = any || ok;
      r.org_x[k] = org[0];
      r.org_y[k] = org[1];
      r.org_z[k] = org[2];
      r.dir_x[k] = -wi[0];
      r.dir_y[k] = -wi[1];
      r.dir_z[k] = -wi[2];
      r.tnear[k] = 0.0f;
      r.tfar[k] = ok ? smax : -INFINITY;
      r.time[k] = 0.0f;
      r.mask[k] = 0xFFFFFFFFu;
      r.id[k] = k;
      r.flags[k] = 0;
    }
    if (any) {
      if (J.coherent == 2) PacketFlags(ctx, valid, r.dir_x, r.dir_y, r.dir_z);
      rtcOccluded16(valid, J.scene, ctx, &r);
    }
    for (int64_t i = s; i < e; ++i) {
      const int k = static_cast<int>(i - s);
      // Embree marks an occluded ray with tfar = -inf
      J.occ[i * J.nl + l] = any && valid[k] && r.tfar[k] == -INFINITY;
    }
  }
}

// Closest hit of the rays [s, e) (e - s <= 16) in one packet.
void Packet16(const Job& J, RTCIntersectContext* ctx, int64_t s, int64_t e) {
  alignas(64) int valid[16];
  alignas(64) RTCRayHit16 rh;
  RTCRay16& r = rh.ray;
  for (int k = 0; k < 16; ++k) {
    const int64_t i = s + k;
    const bool ok = i < e && Valid(J, i);
    valid[k] = ok ? -1 : 0;
    const int64_t j = ok ? i : s;
    r.org_x[k] = J.o[3 * j];
    r.org_y[k] = J.o[3 * j + 1];
    r.org_z[k] = J.o[3 * j + 2];
    r.dir_x[k] = J.d[3 * j];
    r.dir_y[k] = J.d[3 * j + 1];
    r.dir_z[k] = J.d[3 * j + 2];
    r.tnear[k] = ok ? std::max(0.0f, Below(J.tmin[j])) : 0.0f;
    r.tfar[k] = ok ? J.tmax[j] : -INFINITY;
    r.time[k] = 0.0f;
    r.mask[k] = 0xFFFFFFFFu;
    r.id[k] = k;
    r.flags[k] = 0;
    rh.hit.geomID[k] = RTC_INVALID_GEOMETRY_ID;
    rh.hit.primID[k] = RTC_INVALID_GEOMETRY_ID;
  }
  if (J.coherent == 2) PacketFlags(ctx, valid, r.dir_x, r.dir_y, r.dir_z);
  if (J.any_hit) {
    rtcOccluded16(valid, J.scene, ctx, &r);
  } else {
    rtcIntersect16(valid, J.scene, ctx, &rh);
  }
  Hits H;
  for (int64_t i = s; i < e; ++i) {
    const int k = static_cast<int>(i - s);
    if (!valid[k]) {
      Miss(J, i);
      continue;
    }
    if (J.any_hit) {
      // Embree marks an occluded ray with tfar = -inf
      const bool hit = r.tfar[k] == -INFINITY;
      J.t[i] = J.tmax[i];
      J.best[i] = hit ? 0 : -1;
      J.u[i] = J.v[i] = 0.0f;
      NoPoint(J, i);
      continue;
    }
    const unsigned prim = rh.hit.geomID[k] == RTC_INVALID_GEOMETRY_ID ? RTC_INVALID_GEOMETRY_ID : rh.hit.primID[k];
    if (prim == RTC_INVALID_GEOMETRY_ID) {
      Miss(J, i);
      continue;
    }
    H.ray[H.m] = i;
    H.tri[H.m] = static_cast<int32_t>(prim);
    H.t[H.m] = r.tfar[k];
    H.u[H.m] = rh.hit.u[k];
    H.v[H.m] = rh.hit.v[k];
    ++H.m;
  }
  Store(J, H);
  if (J.nl > 0) Shadows16(J, ctx, s, e);
}

// One ray at a time (rtcIntersect1 / rtcOccluded1): the A/B reference for the packets.
void Single(const Job& J, RTCIntersectContext* ctx, int64_t i) {
  if (!Valid(J, i)) {
    Miss(J, i);
    return;
  }
  RTCRayHit rh;
  RTCRay& r = rh.ray;
  r.org_x = J.o[3 * i];
  r.org_y = J.o[3 * i + 1];
  r.org_z = J.o[3 * i + 2];
  r.dir_x = J.d[3 * i];
  r.dir_y = J.d[3 * i + 1];
  r.dir_z = J.d[3 * i + 2];
  r.tnear = std::max(0.0f, Below(J.tmin[i]));
  r.tfar = J.tmax[i];
  r.time = 0.0f;
  r.mask = 0xFFFFFFFFu;
  r.id = 0;
  r.flags = 0;
  rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
  rh.hit.primID = RTC_INVALID_GEOMETRY_ID;
  if (J.any_hit) {
    rtcOccluded1(J.scene, ctx, &r);
    J.t[i] = J.tmax[i];
    J.best[i] = r.tfar == -INFINITY ? 0 : -1;
    J.u[i] = J.v[i] = 0.0f;
    NoPoint(J, i);
    return;
  }
  rtcIntersect1(J.scene, ctx, &rh);
  if (rh.hit.geomID == RTC_INVALID_GEOMETRY_ID) {
    Miss(J, i);
    return;
  }
  Hits H;
  H.m = 1;
  H.ray[0] = i;
  H.tri[0] = static_cast<int32_t>(rh.hit.primID);
  H.t[0] = r.tfar;
  H.u[0] = rh.hit.u;
  H.v[0] = rh.hit.v;
  Store(J, H);
}

void Work(Job& J) {
  RTCIntersectContext ctx;
  rtcInitIntersectContext(&ctx);
  ctx.flags = J.coherent == 1 ? RTC_INTERSECT_CONTEXT_FLAG_COHERENT : RTC_INTERSECT_CONTEXT_FLAG_INCOHERENT;
  for (;;) {
    const int64_t s = J.next.fetch_add(J.chunk);
    if (s >= J.n) return;
    const int64_t e = std::min(s + J.chunk, J.n);
    if (J.packet == 16) {
      for (int64_t p = s; p < e; p += 16) Packet16(J, &ctx, p, std::min(p + 16, e));
    } else {
      for (int64_t i = s; i < e; ++i) Single(J, &ctx, i);
    }
    if (J.done.fetch_add(e - s) + (e - s) == J.n) {
      std::lock_guard<std::mutex> lock(J.mu);
      J.cv.notify_all();
    }
  }
}

int64_t Count(const ffi::AnyBuffer::Dimensions& dims) {
  int64_t c = 1;
  for (auto x : dims) c *= x;
  return c;
}

bool CheckShapes(ffi::Buffer<ffi::F32>& o, ffi::Buffer<ffi::F32>& d, ffi::Buffer<ffi::F32>& tmax, int64_t n,
                 ffi::Buffer<ffi::F32>& tri, int64_t nf, ffi::ResultBuffer<ffi::F32>& t, ffi::ResultBuffer<ffi::S32>& best,
                 ffi::ResultBuffer<ffi::F32>& u, ffi::ResultBuffer<ffi::F32>& v, ffi::ResultBuffer<ffi::F32>& p,
                 ffi::ResultBuffer<ffi::F32>& ng, bool any_hit, int64_t coherent, int64_t packet, int64_t quality,
                 int64_t chunk) {
  // p and ng: (n, 3) where points are asked for (closest hit), else empty
  const int64_t np = Count(p->dimensions());
  return Count(o.dimensions()) == 3 * n && Count(d.dimensions()) == 3 * n && Count(tmax.dimensions()) == n &&
         Count(t->dimensions()) == n && Count(best->dimensions()) == n && Count(u->dimensions()) == n &&
         Count(v->dimensions()) == n && (np == 0 || np == 3 * n) && Count(ng->dimensions()) == np &&
         !(np > 0 && any_hit) && Count(tri.dimensions()) == 9 * nf && nf >= 1 &&
         nf < (int64_t{1} << 31) / 3 && chunk >= 1 && (packet == 1 || packet == 16) && coherent >= 0 &&
         coherent <= 2 && quality >= 0 && quality <= 2;
}

// The rays traced through `scene` on the caller and the pool (or `threads` threads of their own).
void Run(ffi::ThreadPool& pool, std::shared_ptr<Scene> scene, ffi::Buffer<ffi::F32>& o, ffi::Buffer<ffi::F32>& d,
         ffi::Buffer<ffi::F32>& tmin, ffi::Buffer<ffi::F32>& tmax, ffi::Buffer<ffi::F32>& tri,
         ffi::ResultBuffer<ffi::F32>& t, ffi::ResultBuffer<ffi::S32>& best, ffi::ResultBuffer<ffi::F32>& u,
         ffi::ResultBuffer<ffi::F32>& v, ffi::ResultBuffer<ffi::F32>& p, ffi::ResultBuffer<ffi::F32>& ng, int64_t n,
         bool any_hit, bool refine, int64_t coherent, int64_t packet, int64_t chunk, int64_t threads,
         const float* lights = nullptr, int64_t nl = 0, bool* occ = nullptr) {
  const bool points = Count(p->dimensions()) > 0;
  auto job = std::make_shared<Job>();
  Job& J = *job;
  J.o = o.typed_data();
  J.d = d.typed_data();
  J.tmin = tmin.typed_data();
  J.tmax = tmax.typed_data();
  J.tri = tri.typed_data();
  J.n = n;
  J.any_hit = any_hit;
  J.refine = refine;
  J.coherent = coherent;
  J.packet = packet;
  J.scene = scene->scene;
  J.t = t->typed_data();
  J.best = best->typed_data();
  J.u = u->typed_data();
  J.v = v->typed_data();
  J.points = points;
  J.p = points ? p->typed_data() : nullptr;
  J.ng = points ? ng->typed_data() : nullptr;
  J.lights = lights;
  J.nl = nl;
  J.occ = occ;
  J.chunk = chunk;
  const int64_t chunks = (n + chunk - 1) / chunk;
  int64_t workers = threads > 0 ? threads : pool.num_threads();
  std::vector<std::thread> own;
  const bool use_pool = threads <= 0 && workers > 0;
  if (workers <= 0) workers = std::max<int64_t>(1, std::thread::hardware_concurrency());
  const int64_t helpers = std::min(workers, chunks) - 1;
  for (int64_t k = 0; k < helpers; ++k) {
    // A helper that starts after the work is gone finds no chunk and returns; `job` (and through
    // `scene` below, the Embree scene) stays alive for it.
    if (use_pool) {
      pool.Schedule([job, scene] { Work(*job); });
    } else {
      own.emplace_back([job, scene] { Work(*job); });
    }
  }
  Work(J);
  {
    std::unique_lock<std::mutex> lock(J.mu);
    J.cv.wait(lock, [&] { return J.done.load() == J.n; });
  }
  for (auto& th : own) th.join();
}

ffi::Error Trace(ffi::ThreadPool pool, ffi::Buffer<ffi::F32> o, ffi::Buffer<ffi::F32> d, ffi::Buffer<ffi::F32> tmin,
                 ffi::Buffer<ffi::F32> tmax, ffi::Buffer<ffi::F32> tri, ffi::ResultBuffer<ffi::F32> t,
                 ffi::ResultBuffer<ffi::S32> best, ffi::ResultBuffer<ffi::F32> u, ffi::ResultBuffer<ffi::F32> v,
                 ffi::ResultBuffer<ffi::F32> p, ffi::ResultBuffer<ffi::F32> ng, bool any_hit, bool refine,
                 int64_t coherent, int64_t packet, int64_t quality, int64_t chunk, int64_t threads) {
  const int64_t n = Count(tmin.dimensions());
  const int64_t nf = Count(tri.dimensions()) / 9;
  if (!CheckShapes(o, d, tmax, n, tri, nf, t, best, u, v, p, ng, any_hit, coherent, packet, quality, chunk)) {
    return ffi::Error::InvalidArgument("jaxrt_embree_trace: inconsistent array shapes or attributes");
  }
  if (n == 0) return ffi::Error::Success();
  std::string err;
  const uint64_t h = TableHash(pool, threads <= 0 && pool.num_threads() > 0, tri.typed_data(), nf);
  std::shared_ptr<Scene> scene = GetScene(tri.typed_data(), nf, h, static_cast<int>(quality), &err);
  if (!scene) return ffi::Error::Internal("jaxrt_embree_trace: " + err);
  Run(pool, scene, o, d, tmin, tmax, tri, t, best, u, v, p, ng, n, any_hit, refine, coherent, packet, chunk, threads);
  return ffi::Error::Success();
}

// ---------------------------------------------------------------------------------------------
// Keyed calls: the table's hash made once by `TableKey` (a call of its own in the same program,
// taking the same table), then passed to every `TraceKeyed` call beside the table. A path tracer
// traces one table some hundred times a pass (two calls per bounce and chunk); hashing it every
// time (~2-4 ms for the dragon's 31 MB) cost more than the rays of a small chunk. The key is the
// content hash of the very array the keyed call receives, so it follows any edit of the table the
// way the per-call hash does, provided both come from the same value of the program (what
// `traverse_embree.table_key` and `bvh.with_table_key` arrange). As a guard against a key carried
// past an edit of its table, a keyed call compares 64 rows of the table spread over it (and the
// first and last) with the scene's copy and hashes the whole table where they differ.

uint64_t FromKey(const uint32_t* k) { return static_cast<uint64_t>(k[0]) | static_cast<uint64_t>(k[1]) << 32; }

bool SpotCheck(const Scene& s, const float* tri, int64_t nf) {
  if (!s.corners || s.nf != nf) return false;
  constexpr int64_t kRows = 64;
  const int64_t step = std::max<int64_t>(1, nf / kRows);
  auto same = [&](int64_t r) { return std::memcmp(s.corners + 9 * r, tri + 9 * r, 9 * sizeof(float)) == 0; };
  for (int64_t r = 0; r < nf; r += step) {
    if (!same(r)) return false;
  }
  return same(nf - 1);
}

// The kept scene with hash h and a table that passes the spot check, or nullptr.
std::shared_ptr<Scene> FindScene(const float* tri, int64_t nf, uint64_t h) {
  std::lock_guard<std::mutex> lock(g_mu);
  for (auto it = g_scenes.begin(); it != g_scenes.end(); ++it) {
    if ((*it)->hash == h && (*it)->nf == nf) {
      auto s = *it;
      if (!SpotCheck(*s, tri, nf)) return nullptr;
      g_scenes.erase(it);
      g_scenes.push_front(s);
      return s;
    }
  }
  return nullptr;
}

ffi::Error TableKey(ffi::ThreadPool pool, ffi::Buffer<ffi::F32> tri, ffi::ResultBuffer<ffi::U32> key,
                    int64_t quality) {
  const int64_t nf = Count(tri.dimensions()) / 9;
  if (Count(tri.dimensions()) != 9 * nf || nf < 1 || nf >= (int64_t{1} << 31) / 3 || Count(key->dimensions()) != 2 ||
      quality < 0 || quality > 2) {
    return ffi::Error::InvalidArgument("jaxrt_embree_table_key: inconsistent array shapes or attributes");
  }
  const uint64_t h = TableHash(pool, pool.num_threads() > 0, tri.typed_data(), nf);
  std::string err;
  // built here, once, rather than by the first ray query
  if (!GetScene(tri.typed_data(), nf, h, static_cast<int>(quality), &err)) {
    return ffi::Error::Internal("jaxrt_embree_table_key: " + err);
  }
  key->typed_data()[0] = static_cast<uint32_t>(h);
  key->typed_data()[1] = static_cast<uint32_t>(h >> 32);
  return ffi::Error::Success();
}

ffi::Error TraceKeyed(ffi::ThreadPool pool, ffi::Buffer<ffi::F32> o, ffi::Buffer<ffi::F32> d,
                      ffi::Buffer<ffi::F32> tmin, ffi::Buffer<ffi::F32> tmax, ffi::Buffer<ffi::F32> tri,
                      ffi::Buffer<ffi::U32> key, ffi::ResultBuffer<ffi::F32> t, ffi::ResultBuffer<ffi::S32> best,
                      ffi::ResultBuffer<ffi::F32> u, ffi::ResultBuffer<ffi::F32> v, ffi::ResultBuffer<ffi::F32> p,
                      ffi::ResultBuffer<ffi::F32> ng, bool any_hit, bool refine, int64_t coherent, int64_t packet,
                      int64_t quality, int64_t chunk, int64_t threads) {
  const int64_t n = Count(tmin.dimensions());
  const int64_t nf = Count(tri.dimensions()) / 9;
  if (!CheckShapes(o, d, tmax, n, tri, nf, t, best, u, v, p, ng, any_hit, coherent, packet, quality, chunk) ||
      Count(key.dimensions()) != 2) {
    return ffi::Error::InvalidArgument("jaxrt_embree_trace_keyed: inconsistent array shapes or attributes");
  }
  if (n == 0) return ffi::Error::Success();
  std::shared_ptr<Scene> scene = FindScene(tri.typed_data(), nf, FromKey(key.typed_data()));
  if (!scene) {
    // evicted by other tables since the key was made, or the key does not belong to this table:
    // the scene of the table's own hash
    std::string err;
    const uint64_t h = TableHash(pool, threads <= 0 && pool.num_threads() > 0, tri.typed_data(), nf);
    scene = GetScene(tri.typed_data(), nf, h, static_cast<int>(quality), &err);
    if (!scene) return ffi::Error::Internal("jaxrt_embree_trace_keyed: " + err);
  }
  Run(pool, scene, o, d, tmin, tmax, tri, t, best, u, v, p, ng, n, any_hit, refine, coherent, packet, chunk, threads);
  return ffi::Error::Success();
}

// ---------------------------------------------------------------------------------------------
// Direct-light call: the closest hits (refined, with points and normals) and, in the same pass over
// the rays, each hit's shadow rays to nl point lights (`Shadows16`). A Whitted frame of depth 1
// otherwise made the shadow rays in XLA from the hits (about ten passes over the rays) and traced
// them in a second call that hashed the table again; here each packet's shadow rays are traced
// right after its camera rays, while their triangles and hit data are in cache.
ffi::Error Direct(ffi::ThreadPool pool, ffi::Buffer<ffi::F32> o, ffi::Buffer<ffi::F32> d, ffi::Buffer<ffi::F32> tmin,
                  ffi::Buffer<ffi::F32> tmax, ffi::Buffer<ffi::F32> tri, ffi::Buffer<ffi::F32> lights,
                  ffi::ResultBuffer<ffi::F32> t, ffi::ResultBuffer<ffi::S32> best, ffi::ResultBuffer<ffi::F32> u,
                  ffi::ResultBuffer<ffi::F32> v, ffi::ResultBuffer<ffi::F32> p, ffi::ResultBuffer<ffi::F32> ng,
                  ffi::ResultBuffer<ffi::PRED> occ, int64_t coherent, int64_t quality, int64_t chunk,
                  int64_t threads) {
  const int64_t n = Count(tmin.dimensions());
  const int64_t nf = Count(tri.dimensions()) / 9;
  const int64_t nl = Count(lights.dimensions()) / 3;
  if (!CheckShapes(o, d, tmax, n, tri, nf, t, best, u, v, p, ng, false, coherent, 16, quality, chunk) ||
      Count(p->dimensions()) != 3 * n || Count(lights.dimensions()) != 3 * nl || Count(occ->dimensions()) != n * nl) {
    return ffi::Error::InvalidArgument("jaxrt_embree_direct: inconsistent array shapes or attributes");
  }
  if (n == 0) return ffi::Error::Success();
  std::string err;
  const uint64_t h = TableHash(pool, threads <= 0 && pool.num_threads() > 0, tri.typed_data(), nf);
  std::shared_ptr<Scene> scene = GetScene(tri.typed_data(), nf, h, static_cast<int>(quality), &err);
  if (!scene) return ffi::Error::Internal("jaxrt_embree_direct: " + err);
  Run(pool, scene, o, d, tmin, tmax, tri, t, best, u, v, p, ng, n, false, true, coherent, 16, chunk, threads,
      lights.typed_data(), nl, occ->typed_data());
  return ffi::Error::Success();
}

}  // namespace

XLA_FFI_DEFINE_HANDLER_SYMBOL(JaxrtEmbreeTrace, Trace,
                              ffi::Ffi::Bind()
                                  .Ctx<ffi::ThreadPool>()
                                  .Arg<ffi::Buffer<ffi::F32>>()  // origins (N,3)
                                  .Arg<ffi::Buffer<ffi::F32>>()  // directions (N,3)
                                  .Arg<ffi::Buffer<ffi::F32>>()  // tmin (N,)
                                  .Arg<ffi::Buffer<ffi::F32>>()  // tmax (N,)
                                  .Arg<ffi::Buffer<ffi::F32>>()  // triangles (F,9), leaf order
                                  .Ret<ffi::Buffer<ffi::F32>>()  // t
                                  .Ret<ffi::Buffer<ffi::S32>>()  // best (leaf order, -1 = miss)
                                  .Ret<ffi::Buffer<ffi::F32>>()  // u
                                  .Ret<ffi::Buffer<ffi::F32>>()  // v
                                  .Ret<ffi::Buffer<ffi::F32>>()  // hit points (N,3), or (0,3): not asked for
                                  .Ret<ffi::Buffer<ffi::F32>>()  // unit geometric normals, as the points
                                  .Attr<bool>("any_hit")
                                  .Attr<bool>("refine")
                                  .Attr<int64_t>("coherent")
                                  .Attr<int64_t>("packet")
                                  .Attr<int64_t>("quality")
                                  .Attr<int64_t>("chunk")
                                  .Attr<int64_t>("threads"));

XLA_FFI_DEFINE_HANDLER_SYMBOL(JaxrtEmbreeTableKey, TableKey,
                              ffi::Ffi::Bind()
                                  .Ctx<ffi::ThreadPool>()
                                  .Arg<ffi::Buffer<ffi::F32>>()  // triangles (F,9), leaf order
                                  .Ret<ffi::Buffer<ffi::U32>>()  // key (2,): the table's hash, low word first
                                  .Attr<int64_t>("quality"));

XLA_FFI_DEFINE_HANDLER_SYMBOL(JaxrtEmbreeTraceKeyed, TraceKeyed,
                              ffi::Ffi::Bind()
                                  .Ctx<ffi::ThreadPool>()
                                  .Arg<ffi::Buffer<ffi::F32>>()  // origins (N,3)
                                  .Arg<ffi::Buffer<ffi::F32>>()  // directions (N,3)
                                  .Arg<ffi::Buffer<ffi::F32>>()  // tmin (N,)
                                  .Arg<ffi::Buffer<ffi::F32>>()  // tmax (N,)
                                  .Arg<ffi::Buffer<ffi::F32>>()  // triangles (F,9), leaf order
                                  .Arg<ffi::Buffer<ffi::U32>>()  // key (2,) of these triangles (TableKey)
                                  .Ret<ffi::Buffer<ffi::F32>>()  // t
                                  .Ret<ffi::Buffer<ffi::S32>>()  // best (leaf order, -1 = miss)
                                  .Ret<ffi::Buffer<ffi::F32>>()  // u
                                  .Ret<ffi::Buffer<ffi::F32>>()  // v
                                  .Ret<ffi::Buffer<ffi::F32>>()  // hit points (N,3), or (0,3): not asked for
                                  .Ret<ffi::Buffer<ffi::F32>>()  // unit geometric normals, as the points
                                  .Attr<bool>("any_hit")
                                  .Attr<bool>("refine")
                                  .Attr<int64_t>("coherent")
                                  .Attr<int64_t>("packet")
                                  .Attr<int64_t>("quality")
                                  .Attr<int64_t>("chunk")
                                  .Attr<int64_t>("threads"));

XLA_FFI_DEFINE_HANDLER_SYMBOL(JaxrtEmbreeDirect, Direct,
                              ffi::Ffi::Bind()
                                  .Ctx<ffi::ThreadPool>()
                                  .Arg<ffi::Buffer<ffi::F32>>()  // origins (N,3)
                                  .Arg<ffi::Buffer<ffi::F32>>()  // directions (N,3)
                                  .Arg<ffi::Buffer<ffi::F32>>()  // tmin (N,)
                                  .Arg<ffi::Buffer<ffi::F32>>()  // tmax (N,)
                                  .Arg<ffi::Buffer<ffi::F32>>()  // triangles (F,9), leaf order
                                  .Arg<ffi::Buffer<ffi::F32>>()  // point lights' positions (L,3)
                                  .Ret<ffi::Buffer<ffi::F32>>()  // t
                                  .Ret<ffi::Buffer<ffi::S32>>()  // best (leaf order, -1 = miss)
                                  .Ret<ffi::Buffer<ffi::F32>>()  // u
                                  .Ret<ffi::Buffer<ffi::F32>>()  // v
                                  .Ret<ffi::Buffer<ffi::F32>>()  // hit points (N,3)
                                  .Ret<ffi::Buffer<ffi::F32>>()  // unit geometric normals (N,3)
                                  .Ret<ffi::Buffer<ffi::PRED>>()  // (N,L) shadow ray blocked
                                  .Attr<int64_t>("coherent")
                                  .Attr<int64_t>("quality")
                                  .Attr<int64_t>("chunk")
                                  .Attr<int64_t>("threads"));
