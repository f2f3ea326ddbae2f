// Stackless BVH traversal on the CPU as an XLA FFI custom call (see jaxrt/bvh_cpu.py).
//
// The same algorithm and arithmetic as jaxrt/bvh_traverse.py, one ray at a time: the per-ray
// constants of `precompute`, the multiple-threaded links (one pre-order per ray class), the slab
// box test with the far distance widened by `far_scale`, and Woop et al.'s watertight triangle
// test. Every float operation is the float32 operation the XLA path performs, in the same order;
// this file must be compiled with -ffp-contract=off so that no product is fused into a later add
// (the XLA path makes its products opaque for the same reason).
//
// Exact edge signs: a product of two floats is exact in double (24 + 24 significant bits < 53,
// and the exponent range covers float subnormals), so the sign of ax*by - ay*bx is the sign of
// the double difference of the two exact products. The XLA path reaches the same sign through
// the order of the rounded float32 products and, where they are equal, Dekker's TwoProduct; the
// two agree except where the XLA path's error terms underflow (|products| < ~1e-30).
//
// Threads: rays are cut into chunks of consecutive rays (image tiles: coherent) handed out by an
// atomic counter to the caller and to tasks on XLA's intra-op thread pool (std::thread if the
// runtime offers no pool). The caller works too and only waits for chunks already taken, so it
// never waits on a task that has not started (no deadlock when the pool is busy).

#include <algorithm>
#include <atomic>
#include <cmath>
#include <condition_variable>
#include <cstdint>
#include <memory>
#include <mutex>
#include <thread>
#include <vector>

#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

namespace {

struct Job {
  // inputs
  const float* o;
  const float* d;
  const float* tmin;
  const float* tmax;
  const float* box;
  const int32_t* leaf;
  const int32_t* links;
  const float* tri;
  int64_t n, nn, nf;
  bool any_hit, refine;
  float far_scale;
  // outputs
  float* t;
  int32_t* best;
  float* u;
  float* v;
  // work sharing
  int64_t chunk, lanes;
  std::atomic<int64_t> next{0};
  std::atomic<int64_t> done{0};
  std::mutex mu;
  std::condition_variable cv;
};

// Sign of ax*by - ay*bx given the rounded products p1 = fl(ax*by), p2 = fl(ay*bx).
// Without branches on the common path (p1 > p2 is a coin flip for the branch predictor); NaN
// products give 0, as in the XLA path.
inline float EdgeSign(float ax, float by, float ay, float bx, float p1, float p2) {
  float s = static_cast<float>(static_cast<int>(p1 > p2) - static_cast<int>(p1 < p2));
  if (__builtin_expect(p1 == p2, 0)) {
    const double e = static_cast<double>(ax) * by - static_cast<double>(ay) * bx;
    s = static_cast<float>(static_cast<int>(e > 0) - static_cast<int>(e < 0));
  }
  return s;
}

// One ray's traversal state (the XLA path's per-lane state plus its constants).
struct Ray {
  float ox, oy, oz, ix, iy, iz, sx, sy, sz, t_lo, t_best, bu, bv;
  int kx, ky, kz;
  const int32_t* links;  // this ray class's (hit, miss) rows
  int64_t node, steps, i;
  int32_t best;
};

inline void Start(const Job& J, int64_t i, Ray& r) {
  const float dir[3] = {J.d[3 * i], J.d[3 * i + 1], J.d[3 * i + 2]};
  r.ox = J.o[3 * i];
  r.oy = J.o[3 * i + 1];
  r.oz = J.o[3 * i + 2];
  float inv[3];
  for (int k = 0; k < 3; ++k) {
    const float dk = dir[k];
    const float ds = std::fabs(dk) < 1e-20f ? (std::signbit(dk) ? -1e-20f : 1e-20f) : dk;
    inv[k] = 1.0f / ds;
  }
  r.ix = inv[0];
  r.iy = inv[1];
  r.iz = inv[2];
  int kz = 0;  // first index of the largest |d| (jnp.argmax)
  if (std::fabs(dir[1]) > std::fabs(dir[kz])) kz = 1;
  if (std::fabs(dir[2]) > std::fabs(dir[kz])) kz = 2;
  int kx = (kz + 1) % 3, ky = (kx + 1) % 3;
  const float dz = dir[kz];
  const bool flip = dz < 0;  // swap kx and ky to keep the winding
  if (flip) std::swap(kx, ky);
  r.kx = kx;
  r.ky = ky;
  r.kz = kz;
  r.sx = dir[kx] / dz;
  r.sy = dir[ky] / dz;
  r.sz = 1.0f / dz;
  r.links = J.links + 2 * (static_cast<int64_t>(2 * kz + (flip ? 1 : 0)) * J.nn);
  r.t_lo = J.tmin[i];
  r.t_best = J.tmax[i];
  r.best = -1;
  r.bu = r.bv = 0.0f;
  r.node = 0;
  r.steps = 0;
  r.i = i;
}

// t of the ray's plane intersection with its hit triangle in double (bvh_traverse.refine_t's
// double-float evaluation, done natively): differences of floats and products of those are exact
// in double, so the float32 test's eps / cos(angle) error on grazing hits goes. Kept as the float32
// t where the double result is not finite or strays by more than 1 %, as there.
inline float RefineT(const Job& J, const Ray& r) {
  const float* T = J.tri + 9 * static_cast<int64_t>(r.best);
  const float* o = J.o + 3 * r.i;
  const float* d = J.d + 3 * r.i;
  double e1[3], e2[3], a[3];
  for (int k = 0; k < 3; ++k) {
    e1[k] = static_cast<double>(T[3 + k]) - T[k];
    e2[k] = static_cast<double>(T[6 + k]) - T[k];
    a[k] = static_cast<double>(T[k]) - o[k];
  }
  const double n[3] = {e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0]};
  const double num = n[0] * a[0] + n[1] * a[1] + n[2] * a[2];
  const double den = n[0] * d[0] + n[1] * d[1] + n[2] * d[2];
  const float t32 = r.t_best;
  const float t = static_cast<float>(num / den);
  const bool good = den != 0 && std::isfinite(t) && std::fabs(t - t32) <= 1e-2f * std::fabs(t32) + 1e-30f;
  return good ? t : t32;
}

inline void Finish(const Job& J, const Ray& r) {
  J.t[r.i] = (J.refine && r.best >= 0) ? RefineT(J, r) : r.t_best;
  J.best[r.i] = r.best;
  J.u[r.i] = r.bu;
  J.v[r.i] = r.bv;
}

// One traversal step (box test, leaf triangles, next node); false when the ray has ended.
inline bool Step(const Job& J, Ray& r) {
  // Each node is visited at most once per ray; the cap only guards against a corrupt tree.
  if (r.node < 0 || r.node >= J.nn || r.steps > J.nn) return false;
  ++r.steps;
  const int64_t node = r.node;
  const int32_t* lk = r.links + 2 * node;
  const float* b = J.box + 6 * node;
  const float ox = r.ox, oy = r.oy, oz = r.oz;
  const float t0x = (b[0] - ox) * r.ix, t1x = (b[3] - ox) * r.ix;
  const float t0y = (b[1] - oy) * r.iy, t1y = (b[4] - oy) * r.iy;
  const float t0z = (b[2] - oz) * r.iz, t1z = (b[5] - oz) * r.iz;
  float t_near = std::max(std::max(std::min(t0x, t1x), std::min(t0y, t1y)), std::min(t0z, t1z));
  t_near = std::max(t_near, r.t_lo);
  float t_far = std::min(std::min(std::max(t0x, t1x), std::max(t0y, t1y)), std::max(t0z, t1z));
  t_far = std::min(t_far * J.far_scale, r.t_best);
  const bool box_hit = t_near <= t_far;
  const int64_t nxt = lk[box_hit ? 0 : 1];
  if (nxt >= 0) {
    // The next node's rows, while this step's triangles are tested (they are often cache misses).
    __builtin_prefetch(J.box + 6 * nxt);
    __builtin_prefetch(r.links + 2 * nxt);
    __builtin_prefetch(J.leaf + 2 * nxt);
  }
  bool any_h = false;
  const int32_t count = J.leaf[2 * node + 1];
  if (box_hit && count > 0) {
    const int32_t first = J.leaf[2 * node];
    const int kx = r.kx, ky = r.ky, kz = r.kz;
    for (int32_t j = 0; j < count; ++j) {
      const int64_t idx = static_cast<int64_t>(first) + j;
      if (idx < 0 || idx >= J.nf) break;
      const float* v = J.tri + 9 * idx;
      float X[3], Y[3], Z[3];
      for (int w = 0; w < 3; ++w) {
        const float q[3] = {v[3 * w] - ox, v[3 * w + 1] - oy, v[3 * w + 2] - oz};
        const float px = q[kx], py = q[ky], pz = q[kz];
        X[w] = px - r.sx * pz;
        Y[w] = py - r.sy * pz;
        Z[w] = r.sz * pz;
      }
      const float ax = X[0], bx = X[1], cx = X[2], ay = Y[0], by = Y[1], cy = Y[2];
      // Edge functions (c, b), (a, c), (b, a): p1 = x1*y2, p2 = y1*x2.
      const float pu1 = cx * by, pu2 = cy * bx;
      const float pv1 = ax * cy, pv2 = ay * cx;
      const float pw1 = bx * ay, pw2 = by * ax;
      const float su = EdgeSign(cx, by, cy, bx, pu1, pu2);
      const float sv = EdgeSign(ax, cy, ay, cx, pv1, pv2);
      const float sw = EdgeSign(bx, ay, by, ax, pw1, pw2);
      const bool inside = ((su >= 0) & (sv >= 0) & (sw >= 0)) | ((su <= 0) & (sv <= 0) & (sw <= 0));
      if (!inside) continue;
      const float U = std::fabs(pu1 - pu2) * su;
      const float V = std::fabs(pv1 - pv2) * sv;
      const float W = std::fabs(pw1 - pw2) * sw;
      const float det = U + V + W;
      if (!(det != 0.0f)) continue;
      const float t = (U * Z[0] + V * Z[1] + W * Z[2]) / det;
      if (!(t >= r.t_lo && t <= r.t_best)) continue;
      any_h = true;
      // Strict < keeps the earlier triangle on exact ties; a first hit at t == tmax counts.
      if (t < r.t_best || r.best < 0) {
        r.t_best = t;
        r.best = static_cast<int32_t>(idx);
        r.bu = V / det;
        r.bv = W / det;
      }
    }
  }
  r.node = (J.any_hit && any_h) ? -1 : nxt;
  return r.node >= 0;
}

// Rays [s, e) with `lanes` rays in flight, stepped round-robin: their memory accesses are
// independent, so the core overlaps one ray's cache misses with the others' work.
void TraceRange(const Job& J, int64_t s, int64_t e) {
  constexpr int kMaxLanes = 32;
  Ray lane[kMaxLanes];
  const int k = static_cast<int>(std::min<int64_t>(std::min<int64_t>(J.lanes, kMaxLanes), e - s));
  int64_t next = s;
  int live = 0;
  for (int l = 0; l < k; ++l) {
    Start(J, next++, lane[l]);
    ++live;
  }
  bool active[kMaxLanes];
  for (int l = 0; l < k; ++l) active[l] = true;
  while (live > 0) {
    for (int l = 0; l < k; ++l) {
      if (!active[l]) continue;
      if (!Step(J, lane[l])) {
        Finish(J, lane[l]);
        if (next < e) {
          Start(J, next++, lane[l]);
        } else {
          active[l] = false;
          --live;
        }
      }
    }
  }
}

void Work(Job& J) {
  for (;;) {
    const int64_t s = J.next.fetch_add(J.chunk);
    if (s >= J.n) return;
    const int64_t e = std::min(s + J.chunk, J.n);
    TraceRange(J, s, e);
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

ffi::Error Traverse(ffi::ThreadPool pool, ffi::Buffer<ffi::F32> o, ffi::Buffer<ffi::F32> d,
                    ffi::Buffer<ffi::F32> tmin, ffi::Buffer<ffi::F32> tmax, ffi::Buffer<ffi::F32> box,
                    ffi::Buffer<ffi::S32> leaf, ffi::Buffer<ffi::S32> links, ffi::Buffer<ffi::F32> tri,
                    ffi::ResultBuffer<ffi::F32> t, ffi::ResultBuffer<ffi::S32> best, ffi::ResultBuffer<ffi::F32> u,
                    ffi::ResultBuffer<ffi::F32> v, bool any_hit, bool refine, float far_scale, int64_t chunk, int64_t threads,
                    int64_t lanes) {
  const int64_t n = Count(tmin.dimensions());
  const int64_t nn = Count(box.dimensions()) / 6;
  const int64_t nf = Count(tri.dimensions()) / 9;
  if (Count(o.dimensions()) != 3 * n || Count(d.dimensions()) != 3 * n || Count(tmax.dimensions()) != n ||
      Count(t->dimensions()) != n || Count(best->dimensions()) != n || Count(u->dimensions()) != n ||
      Count(v->dimensions()) != n || Count(leaf.dimensions()) != 2 * nn || Count(links.dimensions()) != 12 * nn ||
      nn < 1 || chunk < 1 || lanes < 1) {
    return ffi::Error::InvalidArgument("jaxrt_bvh_traverse: inconsistent array shapes");
  }
  if (n == 0) return ffi::Error::Success();
  auto job = std::make_shared<Job>();
  Job& J = *job;
  J.o = o.typed_data();
  J.d = d.typed_data();
  J.tmin = tmin.typed_data();
  J.tmax = tmax.typed_data();
  J.box = box.typed_data();
  J.leaf = leaf.typed_data();
  J.links = links.typed_data();
  J.tri = tri.typed_data();
  J.n = n;
  J.nn = nn;
  J.nf = nf;
  J.any_hit = any_hit;
  J.refine = refine;
  J.far_scale = far_scale;
  J.t = t->typed_data();
  J.best = best->typed_data();
  J.u = u->typed_data();
  J.v = v->typed_data();
  J.chunk = chunk;
  J.lanes = lanes;
  const int64_t chunks = (n + chunk - 1) / chunk;
  int64_t workers = threads > 0 ? threads : pool.num_threads();
  std::vector<std::thread> own;
  const bool use_pool = threads <= 0 && workers > 0;
  if (workers <= 0) workers = std::max<int64_t>(1, std::thread::hardware_concurrency());
  const int64_t helpers = std::min(workers, chunks) - 1;
  for (int64_t k = 0; k < helpers; ++k) {
    // A helper that starts after the work is gone finds no chunk and returns; `job` keeps the
    // counters alive for it (the buffers are not touched then).
    if (use_pool) {
      pool.Schedule([job] { Work(*job); });
    } else {
      own.emplace_back([job] { Work(*job); });
    }
  }
  Work(J);
  {
    std::unique_lock<std::mutex> lock(J.mu);
    J.cv.wait(lock, [&] { return J.done.load() == J.n; });
  }
  for (auto& th : own) th.join();
  return ffi::Error::Success();
}

}  // namespace

XLA_FFI_DEFINE_HANDLER_SYMBOL(JaxrtBvhTraverse, Traverse,
                              ffi::Ffi::Bind()
                                  .Ctx<ffi::ThreadPool>()
                                  .Arg<ffi::Buffer<ffi::F32>>()  // origins (N,3)
                                  .Arg<ffi::Buffer<ffi::F32>>()  // directions (N,3)
                                  .Arg<ffi::Buffer<ffi::F32>>()  // tmin (N,)
                                  .Arg<ffi::Buffer<ffi::F32>>()  // tmax (N,)
                                  .Arg<ffi::Buffer<ffi::F32>>()  // node_box (nn,6)
                                  .Arg<ffi::Buffer<ffi::S32>>()  // node_leaf (nn,2)
                                  .Arg<ffi::Buffer<ffi::S32>>()  // links (6nn,2)
                                  .Arg<ffi::Buffer<ffi::F32>>()  // triangles (F,9)
                                  .Ret<ffi::Buffer<ffi::F32>>()  // t
                                  .Ret<ffi::Buffer<ffi::S32>>()  // best (leaf order, -1 = miss)
                                  .Ret<ffi::Buffer<ffi::F32>>()  // u
                                  .Ret<ffi::Buffer<ffi::F32>>()  // v
                                  .Attr<bool>("any_hit")
                                  .Attr<bool>("refine")
                                  .Attr<float>("far_scale")
                                  .Attr<int64_t>("chunk")
                                  .Attr<int64_t>("threads")
                                  .Attr<int64_t>("lanes"));
