// The numeric phase of lieax's multifrontal block Cholesky (lieax/factorgraph/_native_cholesky.py):
// H = L L^T of a symmetric block matrix whose symbolic analysis (ordering, fronts, tree) ran in
// Python (`CholeskyPlan.analyze`), then x = H^{-1} b by forward and back substitution.
//
// Plans live in a registry keyed by a digest of the pattern and the analysis options (a 63-bit
// integer attribute of the custom call): Python registers a plan when its analysis ends and
// releases it when the plan object is collected (reference counted per key, since two plan
// objects of one pattern share a key). A traced solve waits for its plan's analysis in Python, so
// the plan is registered before the program runs; an unknown key is an error naming it.
//
// Numerics (Liu, "The multifrontal method for sparse matrix solution: theory and practice",
// SIAM Review 34, 1992; Duff and Reid, ACM TOMS 9, 1983): fronts in postorder; each front F of
// m = (pivots + updates) d rows is assembled from H's entries whose earlier block is one of its
// pivots and from its children's update matrices (extend-add), then
//   F11 = L11 L11^T (potrf),  L21 = F21 L11^{-T} (trsm),  U = F22 - L21 L21^T (syrk),
// U pushed on a stack that its parent pops. L's columns [L11; L21] are kept per front for the
// substitutions: forward, per front in postorder, y1 = L11^{-1} x_p, x_u -= L21 y1; backward,
// in reverse, x_p = L11^{-T} (y1 - L21^T x_u). Fronts whose dense work is small run in plain
// loops here (a BLAS call costs more than their arithmetic); larger ones call the BLAS and LAPACK
// whose function pointers SciPy exports (set once by `LieaxCholeskyInit`). Not positive definite
// (potrf's info > 0) gives NaN in every entry of that solve's result.
#include <dlfcn.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <memory>
#include <mutex>
#include <string>
#include <unordered_map>
#include <vector>

#include "lieax_ffi.h"

namespace ffi = xla::ffi;

namespace {

// ---- BLAS and LAPACK (SciPy's cython_blas / cython_lapack function pointers) --------------------

template <typename T>
struct Blas {
  using Potrf = void(char*, int*, T*, int*, int*);
  using Trsm = void(char*, char*, char*, char*, int*, int*, T*, T*, int*, T*, int*);
  using Syrk = void(char*, char*, int*, int*, T*, T*, int*, T*, T*, int*);
  using Trsv = void(char*, char*, char*, int*, T*, int*, T*, int*);
  Potrf* potrf = nullptr;
  Trsm* trsm = nullptr;
  Syrk* syrk = nullptr;
  Trsv* trsv = nullptr;
  bool ready() const { return potrf && trsm && syrk && trsv; }
};

Blas<double> blas_d;
Blas<float> blas_s;
template <typename T>
const Blas<T>& blas();
template <>
const Blas<double>& blas<double>() {
  return blas_d;
}
template <>
const Blas<float>& blas<float>() {
  return blas_s;
}

// OpenBLAS's count of threads for calls made on the calling thread (0.3.27 and later), looked up
// in the library that holds the BLAS; null elsewhere (another BLAS: its own setting holds).
using SetLocalThreads = int(int);
SetLocalThreads* set_local_threads = nullptr;

SetLocalThreads* find_local_thread_setter(void* function) {
  Dl_info info;
  if (!dladdr(function, &info) || !info.dli_fname) return nullptr;
  void* library = dlopen(info.dli_fname, RTLD_LAZY | RTLD_NOLOAD);
  if (!library) return nullptr;
  for (const char* prefix : {"", "scipy_"}) {
    for (const char* suffix : {"", "64_", "_64"}) {
      std::string name = std::string(prefix) + "openblas_set_num_threads_local" + suffix;
      if (void* symbol = dlsym(library, name.c_str()))
        return reinterpret_cast<SetLocalThreads*>(symbol);
    }
  }
  return nullptr;
}

// Dense work (multiply-adds) of a front below which it runs in the plain loops below. Measured
// (one solve, one thread, M3500 / sphere2500): 7.5 / 59 ms with the BLAS from 8^3, 9.6 / 55 ms
// from 24^3, 11.6 / 73 ms from 48^3; the BLAS's fixed cost per call outweighs small fronts.
constexpr double kBlasFromWork = 12.0 * 12.0 * 12.0;

// ---- small dense kernels (column-major, lower triangles) ----------------------------------------

// A = L L^T in place (lower triangle of the k x k matrix at a, leading dimension lda); false when
// A is not positive definite.
template <typename T>
bool small_potrf(int k, T* a, int lda) {
  for (int j = 0; j < k; ++j) {
    T* cj = a + static_cast<int64_t>(j) * lda;
    for (int l = 0; l < j; ++l) {
      const T* cl = a + static_cast<int64_t>(l) * lda;
      const T s = cl[j];
      for (int i = j; i < k; ++i) cj[i] -= s * cl[i];
    }
    const T pivot = cj[j];
    if (!(pivot > T(0))) return false;
    const T root = std::sqrt(pivot);
    cj[j] = root;
    const T inverse = T(1) / root;
    for (int i = j + 1; i < k; ++i) cj[i] *= inverse;
  }
  return true;
}

// B := B L^{-T} for B (u x k, ldb) and L (k x k lower, lda).
template <typename T>
void small_trsm(int u, int k, const T* l, int lda, T* b, int ldb) {
  for (int j = 0; j < k; ++j) {
    T* bj = b + static_cast<int64_t>(j) * ldb;
    for (int c = 0; c < j; ++c) {
      const T s = l[j + static_cast<int64_t>(c) * lda];
      const T* bc = b + static_cast<int64_t>(c) * ldb;
      for (int i = 0; i < u; ++i) bj[i] -= s * bc[i];
    }
    const T inverse = T(1) / l[j + static_cast<int64_t>(j) * lda];
    for (int i = 0; i < u; ++i) bj[i] *= inverse;
  }
}

// C -= A A^T (lower triangle of the u x u matrix C, ldc) for A (u x k, lda).
template <typename T>
void small_syrk(int u, int k, const T* a, int lda, T* c, int ldc) {
  for (int l = 0; l < k; ++l) {
    const T* al = a + static_cast<int64_t>(l) * lda;
    for (int j = 0; j < u; ++j) {
      const T s = al[j];
      T* cj = c + static_cast<int64_t>(j) * ldc;
      for (int i = j; i < u; ++i) cj[i] -= s * al[i];
    }
  }
}

// ---- the plan -----------------------------------------------------------------------------------

struct Plan {
  int64_t n = 0, d = 0, p = 0;
  bool single_thread = true;  // below lieax's PARALLEL_FLOPS: BLAS on the calling thread only
  // fronts in postorder: pivot and update blocks (original indices, by elimination position),
  // children (in postorder: their update matrices are the top of the stack when the front
  // starts, the first child deepest), the pairs of H assembled there
  std::vector<int64_t> pivot_start, pivots, update_start, updates, child_start, children;
  std::vector<int64_t> pair_start, pairs;
  std::vector<int64_t> position;        // block -> elimination position
  std::vector<int64_t> rows, cols;      // the pattern's pairs
  std::vector<int64_t> factor_offset;   // per front: start of its columns [L11; L21] (m x k)
  int64_t factor_size = 0;              // scalars of L
  int64_t stack_size = 0;               // peak scalars of the update stack
  int64_t max_rows = 0;                 // largest front (rows)

  int64_t fronts() const { return static_cast<int64_t>(child_start.size()) - 1; }
  int64_t num_pivots(int64_t f) const { return pivot_start[f + 1] - pivot_start[f]; }
  int64_t num_updates(int64_t f) const { return update_start[f + 1] - update_start[f]; }

  // Work arrays, one per concurrent solve, kept between solves (a fresh one costs a page fault
  // per 4 KiB at every call) and freed with the plan.
  std::mutex pool_mutex;
  std::vector<std::unique_ptr<std::vector<char>>> pool;

  std::unique_ptr<std::vector<char>> acquire() {
    std::lock_guard<std::mutex> lock(pool_mutex);
    if (pool.empty()) return std::make_unique<std::vector<char>>();
    auto work = std::move(pool.back());
    pool.pop_back();
    return work;
  }
  void give_back(std::unique_ptr<std::vector<char>> work) {
    std::lock_guard<std::mutex> lock(pool_mutex);
    if (pool.size() < 4) pool.push_back(std::move(work));
  }
};

// ---- the registry -------------------------------------------------------------------------------

struct Entry {
  std::shared_ptr<Plan> plan;
  int references = 0;  // plan objects registered under the key
};

std::mutex registry_mutex;
std::unordered_map<int64_t, Entry> registry;

// `key`'s plan into `plan`.
ffi::Error lookup(int64_t key, std::shared_ptr<Plan>* plan) {
  std::lock_guard<std::mutex> lock(registry_mutex);
  auto it = registry.find(key);
  if (it != registry.end() && it->second.plan) {
    *plan = it->second.plan;
    return ffi::Error::Success();
  }
  return ffi::Error(
      ffi::ErrorCode::kNotFound,
      "lieax multifrontal Cholesky: no plan is registered under key " + std::to_string(key) +
          " in this process (a compiled solve runs only while the CholeskyPlan of its pattern "
          "is alive: analyse the pattern (CholeskyPlan.analyze) in this process and keep it).");
}

// ---- numeric phase ------------------------------------------------------------------------------

// lieax's thread setting for plans of parallel size (`lieax.set_threads`; 0: the library's own).
std::atomic<int> parallel_threads{0};

// Sets OpenBLAS's thread-local count for the calling thread while it lives (0: unchanged).
class BlasThreads {
 public:
  explicit BlasThreads(int threads) : active_(threads > 0 && set_local_threads) {
    if (active_) previous_ = set_local_threads(threads);
  }
  ~BlasThreads() {
    if (active_) set_local_threads(previous_);
  }

 private:
  bool active_;
  int previous_ = 0;
};

template <typename T>
class Numeric {
 public:
  Numeric(const Plan& plan, std::vector<char>& work) : plan_(plan) {
    const int64_t n = plan.n;
    const int64_t scalars = plan.factor_size + plan.stack_size + 2 * plan.max_rows;
    const int64_t bytes = (scalars + 1) * static_cast<int64_t>(sizeof(T)) +
                          n * static_cast<int64_t>(sizeof(int64_t));
    if (static_cast<int64_t>(work.size()) < bytes) work.resize(bytes);
    T* base = reinterpret_cast<T*>(work.data());
    factor_ = base;
    stack_ = factor_ + plan.factor_size;
    gathered_ = stack_ + plan.stack_size;
    product_ = gathered_ + plan.max_rows;
    slot_ = reinterpret_cast<int64_t*>(  // (aligned: the buffer is, and holds one T more)
        (reinterpret_cast<uintptr_t>(product_ + plan.max_rows) + 7) & ~uintptr_t{7});
  }

  // L of H (diag (n, d, d), off (p, d, d), row-major); false when H is not positive definite.
  bool factor(const T* diag, const T* off) {
    const Plan& plan = plan_;
    const int64_t d = plan.d;
    int64_t top = 0;  // scalars on the update stack
    for (int64_t f = 0; f < plan.fronts(); ++f) {
      const int64_t np = plan.num_pivots(f), nu = plan.num_updates(f);
      const int64_t k = np * d, u = nu * d, m = k + u;
      const int64_t* piv = plan.pivots.data() + plan.pivot_start[f];
      const int64_t* upd = plan.updates.data() + plan.update_start[f];
      for (int64_t s = 0; s < np; ++s) slot_[plan.position[piv[s]]] = s;
      for (int64_t s = 0; s < nu; ++s) slot_[plan.position[upd[s]]] = np + s;
      T* l = factor_ + plan.factor_offset[f];
      std::fill(l, l + m * k, T(0));
      // H's diagonal blocks of the pivots
      for (int64_t s = 0; s < np; ++s) {
        const T* block = diag + piv[s] * d * d;
        for (int64_t c = 0; c < d; ++c)
          for (int64_t r = c; r < d; ++r) l[(s * d + r) + (s * d + c) * m] = block[r * d + c];
      }
      // H's off-diagonal blocks whose earlier block is a pivot here: column block = earlier
      for (int64_t q = plan.pair_start[f]; q < plan.pair_start[f + 1]; ++q) {
        const int64_t pair = plan.pairs[q];
        const int64_t a = plan.rows[pair], b = plan.cols[pair];
        const T* block = off + pair * d * d;  // H_ab, row-major
        const bool a_first = plan.position[a] < plan.position[b];
        const int64_t column = slot_[plan.position[a_first ? a : b]];
        const int64_t row = slot_[plan.position[a_first ? b : a]];
        for (int64_t c = 0; c < d; ++c)
          for (int64_t r = 0; r < d; ++r)
            l[(row * d + r) + (column * d + c) * m] =
                a_first ? block[c * d + r] : block[r * d + c];  // H_ba = H_ab^T
      }
      // the update matrix of this front, above its children's on the stack
      const int64_t* kids = plan.children.data() + plan.child_start[f];
      const int64_t num_kids = plan.child_start[f + 1] - plan.child_start[f];
      int64_t first_child = top;
      for (int64_t c = 0; c < num_kids; ++c) {
        const int64_t size = plan.num_updates(kids[c]) * d;
        first_child -= size * size;
      }
      T* update = stack_ + top;
      std::fill(update, update + u * u, T(0));
      // extend-add of the children's update matrices (lower triangles)
      int64_t at = first_child;
      for (int64_t c = 0; c < num_kids; ++c) {
        const int64_t cu_blocks = plan.num_updates(kids[c]), cu = cu_blocks * d;
        const int64_t* cupd = plan.updates.data() + plan.update_start[kids[c]];
        const T* source = stack_ + at;
        for (int64_t jb = 0; jb < cu_blocks; ++jb) {
          const int64_t tj = slot_[plan.position[cupd[jb]]] * d;
          for (int64_t ib = jb; ib < cu_blocks; ++ib) {
            const int64_t ti = slot_[plan.position[cupd[ib]]] * d;
            for (int64_t cj = 0; cj < d; ++cj) {
              const int64_t col = tj + cj;
              const T* src = source + (jb * d + cj) * cu + ib * d;
              const int64_t r0 = ib == jb ? cj : 0;
              T* dst = col < k ? l + col * m + ti : update + (col - k) * u + (ti - k);
              for (int64_t r = r0; r < d; ++r) dst[r] += src[r];
            }
          }
        }
        at += cu * cu;
      }
      // dense factorization of the front
      const bool small = static_cast<double>(k) * k * k / 3 + static_cast<double>(k) * k * u +
                             static_cast<double>(k) * u * u / 2 <
                         kBlasFromWork;
      int ki = static_cast<int>(k), ui = static_cast<int>(u), mi = static_cast<int>(m);
      if (small || !blas<T>().ready()) {
        if (!small_potrf(ki, l, mi)) return false;
        if (u) {
          small_trsm(ui, ki, l, mi, l + k, mi);
          small_syrk(ui, ki, l + k, mi, update, ui);
        }
      } else {
        const Blas<T>& b = blas<T>();
        char lower = 'L', right = 'R', trans = 'T', none = 'N';
        int info = 0;
        b.potrf(&lower, &ki, l, &mi, &info);
        if (info != 0) return false;
        if (u) {
          T one = 1, minus_one = -1;
          b.trsm(&right, &lower, &trans, &none, &ui, &ki, &one, l, &mi, l + k, &mi);
          b.syrk(&lower, &none, &ui, &ki, &minus_one, l + k, &mi, &one, update, &ui);
        }
      }
      // pop the children, push this front's update matrix
      if (first_child != top) std::memmove(stack_ + first_child, update, u * u * sizeof(T));
      top = first_child + u * u;
    }
    return true;
  }

  // x := H^{-1} x (n * d scalars, block-major) with the factor of `factor`.
  void solve(T* x) const {
    const Plan& plan = plan_;
    const int64_t d = plan.d;
    const Blas<T>& b = blas<T>();
    for (int64_t f = 0; f < plan.fronts(); ++f) {
      const int64_t np = plan.num_pivots(f), nu = plan.num_updates(f);
      const int64_t k = np * d, u = nu * d, m = k + u;
      const T* l = factor_ + plan.factor_offset[f];
      gather(x, plan.pivots.data() + plan.pivot_start[f], np, gathered_);
      lower_solve(l, k, m, gathered_, false, b);
      scatter(gathered_, plan.pivots.data() + plan.pivot_start[f], np, x, false);
      if (!u) continue;
      // product = L21 y1
      std::fill(product_, product_ + u, T(0));
      for (int64_t c = 0; c < k; ++c) {
        const T s = gathered_[c];
        const T* column = l + c * m + k;
        for (int64_t r = 0; r < u; ++r) product_[r] += column[r] * s;
      }
      scatter(product_, plan.updates.data() + plan.update_start[f], nu, x, true);
    }
    for (int64_t f = plan.fronts() - 1; f >= 0; --f) {
      const int64_t np = plan.num_pivots(f), nu = plan.num_updates(f);
      const int64_t k = np * d, u = nu * d, m = k + u;
      const T* l = factor_ + plan.factor_offset[f];
      gather(x, plan.pivots.data() + plan.pivot_start[f], np, gathered_);
      if (u) {
        gather(x, plan.updates.data() + plan.update_start[f], nu, product_);
        for (int64_t c = 0; c < k; ++c) {  // y1 -= L21^T x_u
          const T* column = l + c * m + k;
          T s = 0;
          for (int64_t r = 0; r < u; ++r) s += column[r] * product_[r];
          gathered_[c] -= s;
        }
      }
      lower_solve(l, k, m, gathered_, true, b);
      scatter(gathered_, plan.pivots.data() + plan.pivot_start[f], np, x, false);
    }
  }

 private:
  void gather(const T* x, const int64_t* blocks, int64_t count, T* out) const {
    const int64_t d = plan_.d;
    for (int64_t s = 0; s < count; ++s)
      std::memcpy(out + s * d, x + blocks[s] * d, d * sizeof(T));
  }
  void scatter(const T* in, const int64_t* blocks, int64_t count, T* x, bool subtract) const {
    const int64_t d = plan_.d;
    for (int64_t s = 0; s < count; ++s) {
      T* target = x + blocks[s] * d;
      if (subtract) {
        for (int64_t r = 0; r < d; ++r) target[r] -= in[s * d + r];
      } else {
        std::memcpy(target, in + s * d, d * sizeof(T));
      }
    }
  }
  // y := L^{-1} y or L^{-T} y for the k x k lower triangle at l (leading dimension m).
  static void lower_solve(const T* l, int64_t k, int64_t m, T* y, bool transpose,
                          const Blas<T>& b) {
    if (k >= 64 && b.ready()) {
      char lower = 'L', trans = transpose ? 'T' : 'N', none = 'N';
      int ki = static_cast<int>(k), mi = static_cast<int>(m), one = 1;
      b.trsv(&lower, &trans, &none, &ki, const_cast<T*>(l), &mi, y, &one);
      return;
    }
    if (!transpose) {
      for (int64_t c = 0; c < k; ++c) {
        const T* column = l + c * m;
        const T v = y[c] / column[c];
        y[c] = v;
        for (int64_t r = c + 1; r < k; ++r) y[r] -= column[r] * v;
      }
    } else {
      for (int64_t c = k - 1; c >= 0; --c) {
        const T* column = l + c * m;
        T s = y[c];
        for (int64_t r = c + 1; r < k; ++r) s -= column[r] * y[r];
        y[c] = s / column[c];
      }
    }
  }

  const Plan& plan_;
  T* factor_;
  T* stack_;
  T* gathered_;
  T* product_;
  int64_t* slot_;
};

// ---- building a plan from the analysis ---------------------------------------------------------

// The plan of Python's analysis (fronts in elimination order, `children` in that numbering,
// blocks as elimination positions), renumbered into postorder; null when it is inconsistent.
std::shared_ptr<Plan> build_plan(int64_t n, int64_t d, int64_t p, const int64_t* rows,
                                 const int64_t* cols, const int64_t* order, int64_t fronts,
                                 const int64_t* pivot_start, const int64_t* pivots,
                                 const int64_t* update_start, const int64_t* updates,
                                 const int64_t* child_start, const int64_t* children,
                                 bool single_thread) {
  if (n <= 0 || d <= 0 || p < 0 || fronts <= 0) return nullptr;
  auto plan = std::make_shared<Plan>();
  plan->n = n, plan->d = d, plan->p = p, plan->single_thread = single_thread;
  plan->rows.assign(rows, rows + p);
  plan->cols.assign(cols, cols + p);
  plan->position.assign(n, -1);
  for (int64_t i = 0; i < n; ++i) {
    if (order[i] < 0 || order[i] >= n || plan->position[order[i]] >= 0) return nullptr;
    plan->position[order[i]] = i;
  }
  for (int64_t q = 0; q < p; ++q)
    if (rows[q] < 0 || rows[q] >= n || cols[q] < 0 || cols[q] >= n || rows[q] == cols[q])
      return nullptr;
  // postorder: depth first from each root, children in the given order
  std::vector<int64_t> parent(fronts, -1);
  for (int64_t f = 0; f < fronts; ++f)
    for (int64_t c = child_start[f]; c < child_start[f + 1]; ++c) {
      if (children[c] < 0 || children[c] >= f || parent[children[c]] >= 0) return nullptr;
      parent[children[c]] = f;
    }
  for (int64_t f = 0; f < fronts; ++f)  // a root's update rows would go nowhere
    if (parent[f] < 0 && update_start[f + 1] > update_start[f]) return nullptr;
  std::vector<int64_t> post;
  post.reserve(fronts);
  std::vector<std::pair<int64_t, int64_t>> stack;  // (front, next child)
  for (int64_t root = 0; root < fronts; ++root) {
    if (parent[root] >= 0) continue;
    stack.emplace_back(root, child_start[root]);
    while (!stack.empty()) {
      auto& [f, next] = stack.back();
      if (next < child_start[f + 1]) {
        const int64_t c = children[next++];
        stack.emplace_back(c, child_start[c]);
      } else {
        post.push_back(f);
        stack.pop_back();
      }
    }
  }
  if (static_cast<int64_t>(post.size()) != fronts) return nullptr;
  std::vector<int64_t> renumbered(fronts);
  for (int64_t i = 0; i < fronts; ++i) renumbered[post[i]] = i;
  std::vector<int64_t> front_of(n, -1);  // elimination position -> front (new numbering)
  plan->pivot_start.push_back(0);
  plan->update_start.push_back(0);
  plan->child_start.push_back(0);
  for (int64_t f : post) {
    // a front's rows in elimination order, its pivots before its updates (the assembly writes
    // lower triangles by slot)
    int64_t last = -1;
    for (int64_t s = pivot_start[f]; s < pivot_start[f + 1]; ++s) {
      if (pivots[s] <= last) return nullptr;
      last = pivots[s];
    }
    for (int64_t s = update_start[f]; s < update_start[f + 1]; ++s) {
      if (updates[s] <= last) return nullptr;
      last = updates[s];
    }
    for (int64_t s = pivot_start[f]; s < pivot_start[f + 1]; ++s) {
      const int64_t at = pivots[s];
      if (at < 0 || at >= n || front_of[at] >= 0) return nullptr;
      front_of[at] = static_cast<int64_t>(plan->pivot_start.size()) - 1;
      plan->pivots.push_back(order[at]);
    }
    for (int64_t s = update_start[f]; s < update_start[f + 1]; ++s) {
      if (updates[s] < 0 || updates[s] >= n) return nullptr;
      plan->updates.push_back(order[updates[s]]);
    }
    for (int64_t c = child_start[f]; c < child_start[f + 1]; ++c)
      plan->children.push_back(renumbered[children[c]]);
    plan->pivot_start.push_back(static_cast<int64_t>(plan->pivots.size()));
    plan->update_start.push_back(static_cast<int64_t>(plan->updates.size()));
    plan->child_start.push_back(static_cast<int64_t>(plan->children.size()));
  }
  for (int64_t i = 0; i < n; ++i)
    if (front_of[i] < 0) return nullptr;  // every block is a pivot of one front
  // the pairs of H, in the front where their earlier block is a pivot
  std::vector<int64_t> owner(p), count(fronts + 1, 0);
  for (int64_t q = 0; q < p; ++q) {
    owner[q] = front_of[std::min(plan->position[rows[q]], plan->position[cols[q]])];
    ++count[owner[q] + 1];
  }
  for (int64_t f = 0; f < fronts; ++f) count[f + 1] += count[f];
  plan->pair_start = count;
  plan->pairs.resize(p);
  for (int64_t q = 0; q < p; ++q) plan->pairs[count[owner[q]]++] = q;
  // every row of a front's entries and of its children's updates is one of its rows
  std::vector<int64_t> mark(n, -1);
  int64_t top = 0, peak = 0;
  plan->factor_offset.resize(fronts);
  for (int64_t f = 0; f < fronts; ++f) {
    const int64_t np = plan->num_pivots(f), nu = plan->num_updates(f);
    for (int64_t s = plan->pivot_start[f]; s < plan->pivot_start[f + 1]; ++s)
      mark[plan->pivots[s]] = f;
    for (int64_t s = plan->update_start[f]; s < plan->update_start[f + 1]; ++s)
      mark[plan->updates[s]] = f;
    for (int64_t q = plan->pair_start[f]; q < plan->pair_start[f + 1]; ++q) {
      const int64_t pair = plan->pairs[q];
      if (mark[rows[pair]] != f || mark[cols[pair]] != f) return nullptr;
    }
    const int64_t k = np * d, u = nu * d, m = k + u;
    peak = std::max(peak, top + u * u);  // above its children's, which it then replaces
    for (int64_t c = plan->child_start[f]; c < plan->child_start[f + 1]; ++c) {
      const int64_t child = plan->children[c];
      for (int64_t s = plan->update_start[child]; s < plan->update_start[child + 1]; ++s)
        if (mark[plan->updates[s]] != f) return nullptr;
      const int64_t cu = plan->num_updates(child) * d;
      top -= cu * cu;
    }
    if (top < 0) return nullptr;
    top += u * u;
    plan->factor_offset[f] = plan->factor_size;
    plan->factor_size += m * k;
    plan->max_rows = std::max(plan->max_rows, m);
  }
  plan->stack_size = peak;
  return plan;
}

// ---- the handler --------------------------------------------------------------------------------

// `off` holds `stride` pair blocks per system, the plan's `p` first (a bucketed graph pads them).
template <typename T>
ffi::Error solve_all(Plan& plan, const ffi::AnyBuffer& diag, const ffi::AnyBuffer& off,
                     const ffi::AnyBuffer& rhs, ffi::AnyBuffer& out, int64_t batch,
                     int64_t stride) {
  auto work = plan.acquire();
  {
    Numeric<T> numeric(plan, *work);
    BlasThreads scope(plan.single_thread ? 1 : parallel_threads.load());
    const int64_t n = plan.n, d = plan.d;
    const T* diag_data = static_cast<const T*>(diag.untyped_data());
    const T* off_data = static_cast<const T*>(off.untyped_data());
    const T* rhs_data = static_cast<const T*>(rhs.untyped_data());
    T* x = static_cast<T*>(out.untyped_data());
    for (int64_t b = 0; b < batch; ++b) {
      T* xb = x + b * n * d;
      if (numeric.factor(diag_data + b * n * d * d, off_data + b * stride * d * d)) {
        std::memcpy(xb, rhs_data + b * n * d, n * d * sizeof(T));
        numeric.solve(xb);
      } else {
        std::fill(xb, xb + n * d, std::numeric_limits<T>::quiet_NaN());
      }
    }
  }
  plan.give_back(std::move(work));
  return ffi::Error::Success();
}

bool has_shape(const ffi::AnyBuffer& buffer, std::initializer_list<int64_t> tail,
               int64_t* batch) {
  auto dims = buffer.dimensions();
  const int64_t rank = static_cast<int64_t>(dims.size()), t = static_cast<int64_t>(tail.size());
  if (rank < t) return false;
  int64_t i = rank - t;
  for (int64_t size : tail)
    if (dims[i++] != size) return false;
  int64_t lead = 1;
  for (int64_t j = 0; j < rank - t; ++j) lead *= dims[j];
  if (*batch >= 0 && lead != *batch) return false;
  *batch = lead;
  return true;
}

// The solve by the plan of `key`; `padded`: `off` may hold more pair blocks than the plan has
// (its first `plan.p` are the plan's), as a bucketed factor graph passes them.
ffi::Error solve_checked(int64_t key, const ffi::AnyBuffer& diag, const ffi::AnyBuffer& off,
                         const ffi::AnyBuffer& rhs, ffi::AnyBuffer& out, bool padded) {
  std::shared_ptr<Plan> found;
  if (ffi::Error error = lookup(key, &found); error.failure()) return error;
  Plan& plan = *found;
  int64_t batch = -1;
  auto off_dims = off.dimensions();
  const int64_t stride =
      padded && off_dims.size() >= 3 ? off_dims[off_dims.size() - 3] : plan.p;
  if (stride < plan.p || !has_shape(rhs, {plan.n, plan.d}, &batch) ||
      !has_shape(diag, {plan.n, plan.d, plan.d}, &batch) ||
      !has_shape(off, {stride, plan.d, plan.d}, &batch) ||
      !has_shape(out, {plan.n, plan.d}, &batch))
    return ffi::Error::InvalidArgument(
        "lieax multifrontal Cholesky: the operands' shapes do not match the plan of key " +
        std::to_string(key) + " (" + std::to_string(plan.n) + " blocks of size " +
        std::to_string(plan.d) + ", " + std::to_string(plan.p) + " pairs).");
  const auto type = rhs.element_type();
  if (diag.element_type() != type || off.element_type() != type || out.element_type() != type)
    return ffi::Error::InvalidArgument("lieax multifrontal Cholesky: mixed dtypes.");
  if (type == ffi::DataType::F64)
    return solve_all<double>(plan, diag, off, rhs, out, batch, stride);
  if (type == ffi::DataType::F32)
    return solve_all<float>(plan, diag, off, rhs, out, batch, stride);
  return ffi::Error::InvalidArgument("lieax multifrontal Cholesky: float32 or float64 only.");
}

ffi::Error SolveImpl(int64_t key, ffi::AnyBuffer diag, ffi::AnyBuffer off, ffi::AnyBuffer rhs,
                     ffi::Result<ffi::AnyBuffer> out) {
  return solve_checked(key, diag, off, rhs, *out, false);
}

// The key as an operand: two uint32 words (low, high) per system, the same in each (a batch
// under `vmap` broadcasts them), so that one compiled program serves every plan of its shapes.
ffi::Error SolveKeyedImpl(ffi::AnyBuffer key, ffi::AnyBuffer diag, ffi::AnyBuffer off,
                          ffi::AnyBuffer rhs, ffi::Result<ffi::AnyBuffer> out) {
  if (key.element_type() != ffi::DataType::U32 || key.element_count() < 2)
    return ffi::Error::InvalidArgument(
        "lieax multifrontal Cholesky: the key operand must be two uint32 words.");
  const uint32_t* words = static_cast<const uint32_t*>(key.untyped_data());
  const int64_t value = static_cast<int64_t>((static_cast<uint64_t>(words[1]) << 32) | words[0]);
  return solve_checked(value, diag, off, rhs, *out, true);
}

}  // namespace

LIEAX_FFI_HANDLER(LieaxCholeskySolve, SolveImpl,
                  ffi::Ffi::Bind()
                      .Attr<int64_t>("key")
                      .Arg<ffi::AnyBuffer>()
                      .Arg<ffi::AnyBuffer>()
                      .Arg<ffi::AnyBuffer>()
                      .Ret<ffi::AnyBuffer>());

LIEAX_FFI_HANDLER(LieaxCholeskySolveKeyed, SolveKeyedImpl,
                  ffi::Ffi::Bind()
                      .Arg<ffi::AnyBuffer>()
                      .Arg<ffi::AnyBuffer>()
                      .Arg<ffi::AnyBuffer>()
                      .Arg<ffi::AnyBuffer>()
                      .Ret<ffi::AnyBuffer>());

// The BLAS and LAPACK functions, in the order potrf, trsm, syrk, trsv (double, float).
LIEAX_EXPORT void LieaxCholeskyInit(void* const* double_functions, void* const* float_functions) {
  auto set = [](auto& b, void* const* f) {
    using B = std::remove_reference_t<decltype(b)>;
    b.potrf = reinterpret_cast<typename B::Potrf*>(f[0]);
    b.trsm = reinterpret_cast<typename B::Trsm*>(f[1]);
    b.syrk = reinterpret_cast<typename B::Syrk*>(f[2]);
    b.trsv = reinterpret_cast<typename B::Trsv*>(f[3]);
  };
  set(blas_d, double_functions);
  set(blas_s, float_functions);
  set_local_threads = find_local_thread_setter(double_functions[0]);
}

// lieax's thread setting (`lieax.set_threads`), for plans above lieax's PARALLEL_FLOPS.
LIEAX_EXPORT void LieaxCholeskySetThreads(int threads) { parallel_threads = threads; }

// Whether OpenBLAS's thread-local count was found (the single-threaded scope of small plans).
LIEAX_EXPORT int LieaxCholeskyScopesThreads() { return set_local_threads != nullptr; }

// Registers the plan of Python's analysis under `key` (one more reference); 0, or 1 when the
// plan is inconsistent (a bug in the analysis, nothing registered).
LIEAX_EXPORT int LieaxCholeskyRegister(int64_t key, int64_t n, int64_t d, int64_t p,
                                       const int64_t* rows, const int64_t* cols,
                                       const int64_t* order, int64_t fronts,
                                       const int64_t* pivot_start, const int64_t* pivots,
                                       const int64_t* update_start, const int64_t* updates,
                                       const int64_t* child_start, const int64_t* children,
                                       int single_thread) {
  auto plan = build_plan(n, d, p, rows, cols, order, fronts, pivot_start, pivots, update_start,
                         updates, child_start, children, single_thread != 0);
  if (!plan) return 1;
  {
    std::lock_guard<std::mutex> lock(registry_mutex);
    Entry& entry = registry[key];
    if (!entry.plan) entry.plan = std::move(plan);
    ++entry.references;
  }
  return 0;
}

// Drops one reference to `key`'s plan (its plan object was collected); the last frees it.
LIEAX_EXPORT void LieaxCholeskyRelease(int64_t key) {
  std::lock_guard<std::mutex> lock(registry_mutex);
  auto it = registry.find(key);
  if (it != registry.end() && --it->second.references <= 0) registry.erase(it);
}

// The plan objects registered under `key` (0 when none).
LIEAX_EXPORT int LieaxCholeskyReferences(int64_t key) {
  std::lock_guard<std::mutex> lock(registry_mutex);
  auto it = registry.find(key);
  return it == registry.end() ? 0 : it->second.references;
}
