// The k-d tree of lieax.icp (see lieax/icp/_native_kdtree.py for the layout and the algorithm's
// sources): a build that returns the tree as arrays, and queries that take those arrays.
//
// Every handler takes leading batch dimensions (jax.ffi.ffi_call's vmap_method="expand_dims": an
// operand that is not batched has size 1 there and is shared by the batch) and runs one call
// for the whole batch, its queries spread over helper threads when the work pays (parallel.h:
// the caller never waits for a helper to wake).
#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <limits>
#include <numeric>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "lieax_ffi.h"
#include "parallel.h"

namespace ffi = xla::ffi;

namespace {

// Queries asking for at least this many neighbours in all run on several threads (below, a
// thread's start costs more than it saves; lieax._threads.PARALLEL_NEIGHBOURS).
constexpr int64_t kParallelNeighbours = 32768;
// Queries handed to a thread at a time (dynamic scheduling: query costs differ across a cloud).
constexpr int64_t kChunk = 512;
// A batch of builds of at least this many points in all spreads its trees over threads, and a
// tree's node of at least this many points its two subtrees.
constexpr int64_t kParallelBuild = 65536;
// A thread keeps the scratch memory of its builds of up to this many points for the next one
// (20 MB in float32, 32 MB in float64).
constexpr int64_t kKeptScratch = int64_t{1} << 20;

std::atomic<int> g_threads{0};  // lieax's thread setting (0: one per core)

int MaxThreads() {
  int n = g_threads.load(std::memory_order_relaxed);
  if (n <= 0) n = static_cast<int>(std::thread::hardware_concurrency());
  return std::max(1, n);
}

int ThreadsFor(int64_t work, int64_t parallel_from) {
  return work < parallel_from ? 1 : MaxThreads();
}

// f(begin, end) over [0, n) in chunks of kChunk, on the caller and up to `threads - 1` helpers.
template <typename F>
void ParallelFor(int64_t n, int threads, const F& f) {
  const int64_t chunks = (n + kChunk - 1) / kChunk;
  lieax::Helpers::For(chunks, threads,
                      [&](int64_t c) { f(c * kChunk, std::min(n, (c + 1) * kChunk)); });
}

// The leading (batch) dimensions of the call: those of a result with `core` trailing dimensions;
// Offset gives where batch element b starts in an operand (in units of its core block), the
// operand's size-1 leading dimensions broadcast.
class Batch {
 public:
  Batch(ffi::Span<const int64_t> dims, int core) : lead_(dims.begin(), dims.end() - core) {
    for (int64_t d : lead_) size_ *= d;
  }
  int64_t size() const { return size_; }
  // The block offset of element b in an operand of dimensions `dims` (`core` trailing ones).
  int64_t Offset(ffi::Span<const int64_t> dims, int core, int64_t b) const {
    const int64_t own = static_cast<int64_t>(dims.size()) - core;
    int64_t offset = 0, stride = 1;
    for (int64_t a = static_cast<int64_t>(lead_.size()) - 1, o = own - 1; a >= 0; --a, --o) {
      const int64_t coordinate = b % lead_[a];
      b /= lead_[a];
      const int64_t d = o >= 0 ? dims[o] : 1;
      if (d != 1) offset += coordinate * stride;
      stride *= d;
    }
    return offset;
  }

 private:
  std::vector<int64_t> lead_;
  int64_t size_ = 1;
};

int64_t Core(ffi::Span<const int64_t> dims, int core) {
  int64_t n = 1;
  for (size_t a = dims.size() - core; a < dims.size(); ++a) n *= dims[a];
  return n;
}

// ---- the tree -------------------------------------------------------------------------------

// The nodes a tree of `count` points may need: every leaf holds at least one point.
int64_t NodeCapacity(int64_t count) { return std::max<int64_t>(1, 2 * count - 1); }

// Views of one tree (see lieax/icp/_native_kdtree.py): `order` (N) tree position -> row, the
// first `count` valid; `points` (N, 3) in tree order; `nodes` (C, 4) start, end, split dimension
// (-1: a leaf), right child (the left child follows its parent); `bounds` (C, 2) the largest
// coordinate of the left child and the smallest of the right child along the split dimension;
// `box` (2, 3) the smallest and largest coordinates of the valid points.
template <typename T>
struct Tree {
  const int32_t* order;
  const T* points;
  const int32_t* nodes;
  const T* bounds;
  const T* box;
  int32_t count() const { return nodes[1]; }
};

// The build works on the indices of the points (4 bytes moved per swap) and reads one coordinate
// array at a time (the points' coordinates split into three arrays): per level a partition pass
// over one array, as pykdtree's build, where moving whole points moved 8 times the memory.
template <typename T>
class Builder {
 public:
  Builder(const T* const* coordinates, int32_t* index, int64_t leaf, int32_t* nodes, T* bounds)
      : c_{coordinates[0], coordinates[1], coordinates[2]},
        index_(index),
        leaf_(leaf),
        nodes_(nodes),
        bounds_(bounds) {}

  // The tree of index[start, end) (inside the box lo, hi) from node `next_` on, in preorder, on
  // up to `threads` threads: a node of at least kParallelBuild points builds its right subtree
  // on another thread, into nodes of its own moved in after the left subtree's (the subtrees'
  // index ranges are disjoint; a node's start and end are positions in `index`, not in the
  // nodes). Returns the number of nodes used.
  int64_t Build(int32_t start, int32_t end, const T* box_lo, const T* box_hi, int threads = 1) {
    const int64_t node = next_++;
    if (end - start <= leaf_) return Leaf(node, start, end);
    T lo[3], hi[3];
    std::copy_n(box_lo, 3, lo), std::copy_n(box_hi, 3, hi);
    // The midpoint of the box's longest side (no pass over the points); where one side gets
    // no point, the box shrinks to the points' and splits at its midpoint (both sides then hold
    // points: where rounding puts the midpoint at the smallest coordinate, the largest splits).
    int dim = Longest(lo, hi);
    T cut = lo[dim] + (hi[dim] - lo[dim]) / 2, low, high;
    int32_t mid = Partition(start, end, dim, cut, low, high);
    if (mid == start || mid == end) {
      Bounds(start, end, lo, hi);
      dim = Longest(lo, hi);
      if (!(hi[dim] > lo[dim])) return Leaf(node, start, end);  // repeats: one leaf
      cut = lo[dim] + (hi[dim] - lo[dim]) / 2;
      if (!(cut > lo[dim])) cut = hi[dim];
      mid = Partition(start, end, dim, cut, low, high);
    }
    bounds_[2 * node] = low;
    bounds_[2 * node + 1] = high;
    T left_hi[3], right_lo[3];
    std::copy_n(hi, 3, left_hi), std::copy_n(lo, 3, right_lo);
    left_hi[dim] = low, right_lo[dim] = high;
    int64_t right;
    if (threads > 1 && end - start >= kParallelBuild) {
      const int64_t capacity = NodeCapacity(end - mid);
      std::vector<int32_t> nodes(4 * capacity);
      std::vector<T> bounds(2 * capacity);
      Builder other(c_, index_, leaf_, nodes.data(), bounds.data());
      lieax::Helpers::For(2, 2, [&](int64_t part) {
        if (part == 0) Build(start, mid, lo, left_hi, threads - threads / 2);
        else other.Build(mid, end, right_lo, hi, threads / 2);
      });
      right = next_;
      next_ = other.MoveTo(nodes_, bounds_, right);
    } else {
      Build(start, mid, lo, left_hi);
      right = next_;
      Build(mid, end, right_lo, hi);
    }
    int32_t* out = nodes_ + 4 * node;
    out[0] = start, out[1] = end, out[2] = dim, out[3] = static_cast<int32_t>(right);
    return next_;
  }

  // This builder's nodes moved to `nodes` and `bounds` from node `at` on (right children
  // renumbered); returns the node after them.
  int64_t MoveTo(int32_t* nodes, T* bounds, int64_t at) const {
    for (int64_t i = 0; i < next_; ++i) {
      std::copy_n(nodes_ + 4 * i, 3, nodes + 4 * (at + i));
      const int32_t child = nodes_[4 * i + 3];
      nodes[4 * (at + i) + 3] = child < 0 ? child : static_cast<int32_t>(child + at);
    }
    std::copy_n(bounds_, 2 * next_, bounds + 2 * at);
    return at + next_;
  }

  // The bounding box of the points index[start, end).
  void Bounds(int32_t start, int32_t end, T* lo, T* hi) const {
    for (int d = 0; d < 3; ++d) {
      lo[d] = std::numeric_limits<T>::infinity();
      hi[d] = -std::numeric_limits<T>::infinity();
      for (int32_t i = start; i < end; ++i) {
        const T v = c_[d][index_[i]];
        lo[d] = std::min(lo[d], v), hi[d] = std::max(hi[d], v);
      }
    }
  }

 private:
  static int Longest(const T* lo, const T* hi) {
    int dim = 0;
    for (int d = 1; d < 3; ++d)
      if (hi[d] - lo[d] > hi[dim] - lo[dim]) dim = d;
    return dim;
  }

  int64_t Leaf(int64_t node, int32_t start, int32_t end) {
    int32_t* out = nodes_ + 4 * node;
    out[0] = start, out[1] = end, out[2] = -1, out[3] = -1;
    bounds_[2 * node] = bounds_[2 * node + 1] = 0;
    return next_;
  }

  // The points below `cut` along `dim` first; returns where the others begin, with `low` the
  // largest coordinate below and `high` the smallest at or above the cut. Branch-free (Lomuto's
  // scheme with an unconditional swap): the comparisons are unpredictable, and a branching
  // partition spent most of the build in mispredictions.
  int32_t Partition(int32_t start, int32_t end, int dim, T cut, T& low, T& high) {
    const T* c = c_[dim];
    constexpr T kInf = std::numeric_limits<T>::infinity();
    low = -kInf, high = kInf;
    int32_t i = start;
    for (int32_t k = start; k < end; ++k) {
      const int32_t id = index_[k];
      const T v = c[id];
      const bool below = v < cut;
      index_[k] = index_[i];
      index_[i] = id;
      i += below;
      low = std::max(low, below ? v : -kInf);
      high = std::min(high, below ? kInf : v);
    }
    return i;
  }

  const T* c_[3];
  int32_t* index_;
  int64_t leaf_;
  int32_t* nodes_;
  T* bounds_;
  int64_t next_ = 0;
};

// Builds the tree of the valid, finite rows of `points` (n, 3) into the given arrays (`capacity`
// nodes); unused nodes are zero, the rows past the valid ones hold inf.
template <typename T>
void BuildTree(const T* points, const bool* valid, int64_t n, int64_t leaf, int64_t capacity,
               int32_t* order, T* tree_points, int32_t* nodes, T* bounds, T* box, int threads) {
  // Kept per thread between builds of up to kKeptScratch points: a fresh allocation of a few MB is
  // mapped and faulted in anew by every build (a 181k-point tree took 12-19 ms, 12-15 with these
  // kept).
  thread_local std::vector<T> coordinates;
  thread_local std::vector<int32_t> rows, index;
  coordinates.resize(3 * n);
  T* const split[3] = {coordinates.data(), coordinates.data() + n, coordinates.data() + 2 * n};
  rows.clear();
  rows.reserve(n);
  int32_t rest = 0;
  for (int64_t i = 0; i < n; ++i) {
    const T* q = points + 3 * i;
    if (valid[i] && std::isfinite(q[0]) && std::isfinite(q[1]) && std::isfinite(q[2])) {
      for (int d = 0; d < 3; ++d) split[d][rows.size()] = q[d];
      rows.push_back(static_cast<int32_t>(i));
    } else {
      order[n - 1 - rest++] = static_cast<int32_t>(i);  // (reversed below)
    }
  }
  const int32_t count = static_cast<int32_t>(rows.size());
  std::reverse(order + count, order + n);
  index.resize(count);
  std::iota(index.begin(), index.end(), 0);
  Builder<T> builder(split, index.data(), leaf, nodes, bounds);
  builder.Bounds(0, count, box, box + 3);
  const int64_t used = builder.Build(0, count, box, box + 3, threads);
  std::fill(nodes + 4 * used, nodes + 4 * capacity, 0);
  std::fill(bounds + 2 * used, bounds + 2 * capacity, T(0));
  for (int32_t i = 0; i < count; ++i) {
    const int32_t k = index[i];
    order[i] = rows[k];
    for (int d = 0; d < 3; ++d) tree_points[3 * int64_t{i} + d] = split[d][k];
  }
  std::fill(tree_points + 3 * int64_t{count}, tree_points + 3 * n, std::numeric_limits<T>::infinity());
  if (n > kKeptScratch) {
    std::vector<T>().swap(coordinates);
    std::vector<int32_t>().swap(rows);
    std::vector<int32_t>().swap(index);
  }
}

// ---- searches -------------------------------------------------------------------------------

// The nearest point at a squared distance below `bound` (strictly).
struct Nearest {
  double best;
  int32_t position = -1;
  explicit Nearest(double bound) : best(bound) {}
  double Worst() const { return best; }
  void Add(double d2, int32_t i) {
    if (d2 < best) best = d2, position = i;
  }
};

// The k nearest points at squared distances below `bound` (strictly), nearest first.
struct KNearest {
  int k, found = 0;
  double bound;
  double* d2;
  int32_t* position;
  KNearest(int k, double bound, double* d2, int32_t* position)
      : k(k), bound(bound), d2(d2), position(position) {}
  double Worst() const { return found < k ? bound : d2[k - 1]; }
  void Add(double d, int32_t i) {
    if (!(d < Worst())) return;
    int j = found < k ? found++ : k - 1;
    for (; j > 0 && d2[j - 1] > d; --j) d2[j] = d2[j - 1], position[j] = position[j - 1];
    d2[j] = d, position[j] = i;
  }
};

// Depth-first search with incremental distances to the cells (Arya and Mount, "Algorithms for
// fast vector quantization", 1993; as in nanoflann): `rd` is the squared distance from q to the
// node's cell, `offsets` its per-dimension terms. Leaf distances are computed in T (as pykdtree
// does), the cell bounds in double.
template <typename T, typename Result>
void Search(const Tree<T>& tree, const T* q, int64_t node, double rd, double* offsets,
            Result& result) {
  const int32_t* n = tree.nodes + 4 * node;
  if (n[2] < 0) {
    for (int32_t i = n[0]; i < n[1]; ++i) {
      const T* p = tree.points + 3 * int64_t{i};
      const T dx = q[0] - p[0], dy = q[1] - p[1], dz = q[2] - p[2];
      result.Add(static_cast<double>(dx * dx + dy * dy + dz * dz), i);
    }
    return;
  }
  const int dim = n[2];
  const double below = double(q[dim]) - double(tree.bounds[2 * node]);
  const double above = double(q[dim]) - double(tree.bounds[2 * node + 1]);
  int64_t near_child, far_child;
  double cut;
  if (below + above < 0) {
    near_child = node + 1, far_child = n[3], cut = above * above;
  } else {
    near_child = n[3], far_child = node + 1, cut = below * below;
  }
  Search(tree, q, near_child, rd, offsets, result);
  const double saved = offsets[dim];
  rd += cut - saved;
  if (rd < result.Worst()) {
    offsets[dim] = cut;
    Search(tree, q, far_child, rd, offsets, result);
    offsets[dim] = saved;
  }
}

template <typename T, typename Result>
void Query(const Tree<T>& tree, const T* q, Result& result) {
  if (tree.count() == 0) return;
  double offsets[3], rd = 0;
  for (int d = 0; d < 3; ++d) {
    const double below = double(tree.box[d]) - q[d], above = double(q[d]) - tree.box[3 + d];
    offsets[d] = below > 0 ? below * below : above > 0 ? above * above : 0.0;
    rd += offsets[d];
  }
  if (rd < result.Worst()) Search(tree, q, 0, rd, offsets, result);
}

// ---- handlers -------------------------------------------------------------------------------

ffi::Error CheckCloud(ffi::Span<const int64_t> dims, const char* what) {
  if (dims.size() < 2 || dims[dims.size() - 1] != 3)
    return ffi::Error::InvalidArgument(std::string(what) + " must have shape (..., n, 3)");
  return ffi::Error::Success();
}

ffi::Error Unsupported() {
  return ffi::Error::InvalidArgument("the k-d tree takes float32 or float64 points");
}

// Tree operands of batch element b.
struct TreeBuffers {
  ffi::AnyBuffer order, points, nodes, bounds, box;
  template <typename T>
  Tree<T> At(const Batch& batch, int64_t b) const {
    auto at = [&](const ffi::AnyBuffer& x, int core) {
      return batch.Offset(x.dimensions(), core, b) * Core(x.dimensions(), core);
    };
    return Tree<T>{static_cast<const int32_t*>(order.untyped_data()) + at(order, 1),
                   static_cast<const T*>(points.untyped_data()) + at(points, 2),
                   static_cast<const int32_t*>(nodes.untyped_data()) + at(nodes, 2),
                   static_cast<const T*>(bounds.untyped_data()) + at(bounds, 2),
                   static_cast<const T*>(box.untyped_data()) + at(box, 2)};
  }
};

template <typename T>
ffi::Error BuildTyped(ffi::AnyBuffer points, ffi::Buffer<ffi::PRED> valid, int64_t leaf,
                      ffi::Result<ffi::Buffer<ffi::S32>> order, ffi::Result<ffi::AnyBuffer> tree_points,
                      ffi::Result<ffi::Buffer<ffi::S32>> nodes, ffi::Result<ffi::AnyBuffer> bounds,
                      ffi::Result<ffi::AnyBuffer> box) {
  const auto pd = points.dimensions();
  const int64_t n = pd[pd.size() - 2];
  const int64_t capacity = nodes->dimensions()[nodes->dimensions().size() - 2];
  if (capacity < NodeCapacity(n))
    return ffi::Error::InvalidArgument("the node arrays are too small for the points");
  const Batch batch(order->dimensions(), 1);
  const int threads = ThreadsFor(batch.size() * n, kParallelBuild);
  const int count = static_cast<int>(std::min<int64_t>(threads, batch.size()));
  const int per_tree = std::max(1, threads / count);  // one tree: its subtrees over the threads
  auto build = [&](int64_t b) {
    BuildTree<T>(static_cast<const T*>(points.untyped_data()) + batch.Offset(pd, 2, b) * 3 * n,
                 valid.typed_data() + batch.Offset(valid.dimensions(), 1, b) * n, n, leaf,
                 capacity, order->typed_data() + b * n,
                 static_cast<T*>(tree_points->untyped_data()) + b * 3 * n,
                 nodes->typed_data() + b * 4 * capacity,
                 static_cast<T*>(bounds->untyped_data()) + b * 2 * capacity,
                 static_cast<T*>(box->untyped_data()) + b * 6, per_tree);
  };
  lieax::Helpers::For(batch.size(), count, build);
  return ffi::Error::Success();
}

ffi::Error BuildImpl(ffi::AnyBuffer points, ffi::Buffer<ffi::PRED> valid, int64_t leaf,
                     ffi::Result<ffi::Buffer<ffi::S32>> order, ffi::Result<ffi::AnyBuffer> tree_points,
                     ffi::Result<ffi::Buffer<ffi::S32>> nodes, ffi::Result<ffi::AnyBuffer> bounds,
                     ffi::Result<ffi::AnyBuffer> box) {
  if (auto error = CheckCloud(points.dimensions(), "points"); !error.success()) return error;
  if (leaf < 1) return ffi::Error::InvalidArgument("leaf_size must be positive");
  switch (points.element_type()) {
    case ffi::DataType::F32:
      return BuildTyped<float>(points, valid, leaf, order, tree_points, nodes, bounds, box);
    case ffi::DataType::F64:
      return BuildTyped<double>(points, valid, leaf, order, tree_points, nodes, bounds, box);
    default:
      return Unsupported();
  }
}

// The nearest valid point within `radius` (inclusive): its row (0 for none) and squared
// distance (inf for none); rows not `active` get none.
template <typename T>
ffi::Error NearestTyped(const TreeBuffers& tree, ffi::AnyBuffer queries, ffi::AnyBuffer radius,
                        ffi::Buffer<ffi::PRED> active, ffi::Result<ffi::Buffer<ffi::S32>> slot,
                        ffi::Result<ffi::AnyBuffer> d2) {
  const auto qd = queries.dimensions();
  const int64_t m = qd[qd.size() - 2];
  const Batch batch(slot->dimensions(), 1);
  std::vector<Tree<T>> trees;
  std::vector<const T*> query_rows;
  std::vector<const bool*> active_rows;
  std::vector<double> bounds;
  for (int64_t b = 0; b < batch.size(); ++b) {
    trees.push_back(tree.At<T>(batch, b));
    query_rows.push_back(static_cast<const T*>(queries.untyped_data()) + batch.Offset(qd, 2, b) * 3 * m);
    active_rows.push_back(active.typed_data() + batch.Offset(active.dimensions(), 1, b) * m);
    const double r = static_cast<const T*>(radius.untyped_data())[batch.Offset(radius.dimensions(), 0, b)];
    // d2 <= r^2 accepted: the search keeps d2 < the next double above r^2.
    bounds.push_back(std::nextafter(r * r, std::numeric_limits<double>::infinity()));
  }
  int32_t* slots = slot->typed_data();
  T* distances = static_cast<T*>(d2->untyped_data());
  ParallelFor(batch.size() * m, ThreadsFor(batch.size() * m, kParallelNeighbours),
              [&](int64_t begin, int64_t end) {
                for (int64_t g = begin; g < end; ++g) {
                  const int64_t b = g / m, i = g % m;
                  Nearest result(bounds[b]);
                  if (active_rows[b][i]) Query(trees[b], query_rows[b] + 3 * i, result);
                  const bool found = result.position >= 0;
                  slots[g] = found ? trees[b].order[result.position] : 0;
                  distances[g] = found ? static_cast<T>(result.best)
                                       : std::numeric_limits<T>::infinity();
                }
              });
  return ffi::Error::Success();
}

// track_in_kdtree's query (lieax/icp/_host_kdtree.py): for each active row its nearest valid
// point, its row or -1, and an allowance. With `pairs`, the nearest within twice the radius r and
// the allowance (min(d2, 2r) - d1) / 2 from the nearest and second-nearest distances (r for
// none); without, the nearest within r alone and the allowance 0 (a query far from the target then
// stops early: no point within r is looked for in the shell out to 2r); with one valid point in
// the tree, (2r - d1) / 2 for a match either way, and with none, r. Rows not active get
// (-1, -inf).
template <typename T>
ffi::Error TrackTyped(const TreeBuffers& tree, ffi::AnyBuffer queries, ffi::AnyBuffer radius,
                      ffi::Buffer<ffi::PRED> active, ffi::Buffer<ffi::PRED> pairs,
                      ffi::Result<ffi::Buffer<ffi::S32>> slot, ffi::Result<ffi::AnyBuffer> allowance) {
  const auto qd = queries.dimensions();
  const int64_t m = qd[qd.size() - 2];
  const Batch batch(slot->dimensions(), 1);
  struct Element {
    Tree<T> tree;
    const T* queries;
    const bool* active;
    double radius, bound;
    int k;
    bool pairs;
  };
  std::vector<Element> elements;
  int64_t work = 0;
  for (int64_t b = 0; b < batch.size(); ++b) {
    Element e;
    e.tree = tree.At<T>(batch, b);
    e.queries = static_cast<const T*>(queries.untyped_data()) + batch.Offset(qd, 2, b) * 3 * m;
    e.active = active.typed_data() + batch.Offset(active.dimensions(), 1, b) * m;
    e.radius = static_cast<const T*>(radius.untyped_data())[batch.Offset(radius.dimensions(), 0, b)];
    const bool two = pairs.typed_data()[batch.Offset(pairs.dimensions(), 0, b)];
    e.k = std::min<int>(two ? 2 : 1, e.tree.count());
    e.pairs = two;
    // The host tree's rule: found when d < searched (1 + 8 eps), eps of T.
    const double searched = (two ? 2 : 1) * e.radius;
    const double widened = searched * (1 + 8 * double(std::numeric_limits<T>::epsilon()));
    e.bound = widened * widened;
    work += m * std::max(e.k, 1);
    elements.push_back(e);
  }
  int32_t* slots = slot->typed_data();
  T* allowances = static_cast<T*>(allowance->untyped_data());
  ParallelFor(batch.size() * m, ThreadsFor(work, kParallelNeighbours), [&](int64_t begin, int64_t end) {
    double d2[2];
    int32_t position[2];
    for (int64_t g = begin; g < end; ++g) {
      const Element& e = elements[g / m];
      const int64_t i = g % m;
      if (!e.active[i]) {
        slots[g] = -1, allowances[g] = -std::numeric_limits<T>::infinity();
        continue;
      }
      const double r = e.radius, reach = 2 * r;
      KNearest result(std::max(e.k, 1), e.bound, d2, position);
      Query(e.tree, e.queries + 3 * i, result);
      if (result.found == 0) {  // none within 2r (or at all) stays none within r for moves below r
        const bool far = e.pairs || e.tree.count() == 0;
        slots[g] = -1, allowances[g] = static_cast<T>(far ? r : 0.0);
        continue;
      }
      // distances as the host tree reports them: square roots in T
      const double first = std::sqrt(static_cast<T>(d2[0]));
      double share = 0.0;
      if (e.k == 2) {
        const double second = result.found == 2 ? std::sqrt(static_cast<T>(d2[1])) : reach;
        share = 0.5 * (std::min(second, reach) - first);
      } else if (e.tree.count() == 1) {  // one valid point: no other within any distance
        share = 0.5 * (reach - first);
      }
      slots[g] = e.tree.order[position[0]], allowances[g] = static_cast<T>(share);
    }
  });
  return ffi::Error::Success();
}

// For every valid row (in tree order) its k nearest valid rows, itself among them: calls
// f(b, tree, tree position, count, d2, positions) with count = min(k, valid rows).
template <typename T, typename F>
void EachNeighbourhood(const std::vector<Tree<T>>& trees, int k, const F& f) {
  std::vector<int64_t> starts{0};
  for (const auto& tree : trees) starts.push_back(starts.back() + tree.count());
  const int64_t total = starts.back();
  ParallelFor(total, ThreadsFor(total * k, kParallelNeighbours), [&](int64_t begin, int64_t end) {
    std::vector<double> d2(k);
    std::vector<int32_t> position(k);
    int64_t b = std::upper_bound(starts.begin(), starts.end(), begin) - starts.begin() - 1;
    for (int64_t g = begin; g < end; ++g) {
      while (g >= starts[b + 1]) ++b;
      const Tree<T>& tree = trees[b];
      const int32_t i = static_cast<int32_t>(g - starts[b]);
      const int count = std::min<int>(k, tree.count());
      KNearest result(count, std::numeric_limits<double>::infinity(), d2.data(), position.data());
      Query(tree, tree.points + 3 * int64_t{i}, result);
      f(b, tree, i, result.found, d2.data(), position.data());
    }
  });
}

template <typename T>
ffi::Error SpacingTyped(const TreeBuffers& tree, ffi::Result<ffi::AnyBuffer> spacing) {
  const Batch batch(spacing->dimensions(), 1);
  const int64_t n = spacing->dimensions()[spacing->dimensions().size() - 1];
  std::vector<Tree<T>> trees;
  for (int64_t b = 0; b < batch.size(); ++b) trees.push_back(tree.At<T>(batch, b));
  T* out = static_cast<T*>(spacing->untyped_data());
  std::fill(out, out + batch.size() * n, T(0));
  EachNeighbourhood<T>(trees, 2, [&](int64_t b, const Tree<T>& t, int32_t i, int found,
                                     const double* d2, const int32_t*) {
    out[b * n + t.order[i]] = found < 2 ? std::numeric_limits<T>::infinity()
                                        : std::sqrt(static_cast<T>(d2[1]));
  });
  return ffi::Error::Success();
}

// Builds one tree per batch element of points (..., n, 3) / valid (..., n) into scratch arrays.
template <typename T>
struct ScratchTrees {
  std::vector<int32_t> order, nodes;
  std::vector<T> points, bounds, box;
  std::vector<Tree<T>> trees;
  ScratchTrees(ffi::AnyBuffer cloud, ffi::Buffer<ffi::PRED> valid, const Batch& batch, int64_t leaf) {
    const auto pd = cloud.dimensions();
    const int64_t n = pd[pd.size() - 2], capacity = NodeCapacity(n), size = batch.size();
    order.resize(size * n), points.resize(size * 3 * n), nodes.resize(size * 4 * capacity);
    bounds.resize(size * 2 * capacity), box.resize(size * 6);
    for (int64_t b = 0; b < size; ++b) {
      BuildTree<T>(static_cast<const T*>(cloud.untyped_data()) + batch.Offset(pd, 2, b) * 3 * n,
                   valid.typed_data() + batch.Offset(valid.dimensions(), 1, b) * n, n, leaf,
                   capacity, order.data() + b * n, points.data() + b * 3 * n,
                   nodes.data() + b * 4 * capacity, bounds.data() + b * 2 * capacity,
                   box.data() + b * 6, ThreadsFor(n, kParallelBuild));
    }
    for (int64_t b = 0; b < size; ++b)
      trees.push_back(Tree<T>{order.data() + b * n, points.data() + b * 3 * n,
                              nodes.data() + b * 4 * capacity, bounds.data() + b * 2 * capacity,
                              box.data() + b * 6});
  }
};

template <typename T>
ffi::Error NeighboursTyped(ffi::AnyBuffer points, ffi::Buffer<ffi::PRED> valid, int64_t leaf,
                           ffi::Result<ffi::Buffer<ffi::S32>> rows) {
  const auto rd = rows->dimensions();
  const int64_t n = rd[rd.size() - 2], k = rd[rd.size() - 1];
  const Batch batch(rd, 2);
  ScratchTrees<T> scratch(points, valid, batch, leaf);
  int32_t* out = rows->typed_data();
  std::fill(out, out + batch.size() * n * k, -1);
  EachNeighbourhood<T>(scratch.trees, static_cast<int>(k),
                       [&](int64_t b, const Tree<T>& t, int32_t i, int found, const double*,
                           const int32_t* position) {
                         int32_t* row = out + (b * n + t.order[i]) * k;
                         for (int j = 0; j < found; ++j) row[j] = t.order[position[j]];
                       });
  return ffi::Error::Success();
}

// The six upper entries (00, 01, 02, 11, 12, 22) of the sample covariance of each valid row and
// its k - 1 nearest valid rows, in double about the row: (1/c) sum o o^T - mean(o) mean(o)^T with
// o = p_j - p (small_gicp's sums); 0 in the rows not valid.
template <typename T>
ffi::Error CovariancesTyped(ffi::AnyBuffer points, ffi::Buffer<ffi::PRED> valid, int64_t k,
                            int64_t leaf, ffi::Result<ffi::AnyBuffer> entries) {
  const auto ed = entries->dimensions();
  const int64_t n = ed[ed.size() - 2];
  const Batch batch(ed, 2);
  ScratchTrees<T> scratch(points, valid, batch, leaf);
  T* out = static_cast<T*>(entries->untyped_data());
  std::fill(out, out + batch.size() * n * 6, T(0));
  EachNeighbourhood<T>(scratch.trees, static_cast<int>(k),
                       [&](int64_t b, const Tree<T>& t, int32_t i, int found, const double*,
                           const int32_t* position) {
                         const T* p = t.points + 3 * int64_t{i};
                         double sum[3] = {0, 0, 0}, products[6] = {0, 0, 0, 0, 0, 0};
                         for (int j = 0; j < found; ++j) {
                           const T* q = t.points + 3 * int64_t{position[j]};
                           const double o[3] = {double(q[0]) - p[0], double(q[1]) - p[1],
                                                double(q[2]) - p[2]};
                           for (int a = 0; a < 3; ++a) sum[a] += o[a];
                           products[0] += o[0] * o[0], products[1] += o[0] * o[1];
                           products[2] += o[0] * o[2], products[3] += o[1] * o[1];
                           products[4] += o[1] * o[2], products[5] += o[2] * o[2];
                         }
                         const int pairs[6][2] = {{0, 0}, {0, 1}, {0, 2}, {1, 1}, {1, 2}, {2, 2}};
                         T* row = out + (b * n + t.order[i]) * 6;
                         for (int e = 0; e < 6; ++e) {
                           const double ma = sum[pairs[e][0]] / found, mb = sum[pairs[e][1]] / found;
                           row[e] = static_cast<T>(products[e] / found - ma * mb);
                         }
                       });
  return ffi::Error::Success();
}

#define LIEAX_DISPATCH(type, call)                        \
  switch (type) {                                         \
    case ffi::DataType::F32: {                            \
      using T = float;                                    \
      return call;                                        \
    }                                                     \
    case ffi::DataType::F64: {                            \
      using T = double;                                   \
      return call;                                        \
    }                                                     \
    default:                                              \
      return Unsupported();                               \
  }

ffi::Error NearestImpl(ffi::AnyBuffer order, ffi::AnyBuffer points, ffi::AnyBuffer nodes,
                       ffi::AnyBuffer bounds, ffi::AnyBuffer box, ffi::AnyBuffer queries,
                       ffi::AnyBuffer radius, ffi::Buffer<ffi::PRED> active,
                       ffi::Result<ffi::Buffer<ffi::S32>> slot, ffi::Result<ffi::AnyBuffer> d2) {
  if (auto error = CheckCloud(queries.dimensions(), "queries"); !error.success()) return error;
  const TreeBuffers tree{order, points, nodes, bounds, box};
  LIEAX_DISPATCH(points.element_type(), NearestTyped<T>(tree, queries, radius, active, slot, d2))
}

ffi::Error TrackImpl(ffi::AnyBuffer order, ffi::AnyBuffer points, ffi::AnyBuffer nodes,
                     ffi::AnyBuffer bounds, ffi::AnyBuffer box, ffi::AnyBuffer queries,
                     ffi::AnyBuffer radius, ffi::Buffer<ffi::PRED> active,
                     ffi::Buffer<ffi::PRED> pairs, ffi::Result<ffi::Buffer<ffi::S32>> slot,
                     ffi::Result<ffi::AnyBuffer> allowance) {
  if (auto error = CheckCloud(queries.dimensions(), "queries"); !error.success()) return error;
  const TreeBuffers tree{order, points, nodes, bounds, box};
  LIEAX_DISPATCH(points.element_type(),
                 TrackTyped<T>(tree, queries, radius, active, pairs, slot, allowance))
}

ffi::Error SpacingImpl(ffi::AnyBuffer order, ffi::AnyBuffer points, ffi::AnyBuffer nodes,
                       ffi::AnyBuffer bounds, ffi::AnyBuffer box, ffi::Result<ffi::AnyBuffer> spacing) {
  const TreeBuffers tree{order, points, nodes, bounds, box};
  LIEAX_DISPATCH(points.element_type(), SpacingTyped<T>(tree, spacing))
}

ffi::Error NeighboursImpl(ffi::AnyBuffer points, ffi::Buffer<ffi::PRED> valid, int64_t leaf,
                          ffi::Result<ffi::Buffer<ffi::S32>> rows) {
  if (auto error = CheckCloud(points.dimensions(), "points"); !error.success()) return error;
  LIEAX_DISPATCH(points.element_type(), NeighboursTyped<T>(points, valid, leaf, rows))
}

ffi::Error CovariancesImpl(ffi::AnyBuffer points, ffi::Buffer<ffi::PRED> valid, int64_t k,
                           int64_t leaf, ffi::Result<ffi::AnyBuffer> entries) {
  if (auto error = CheckCloud(points.dimensions(), "points"); !error.success()) return error;
  LIEAX_DISPATCH(points.element_type(), CovariancesTyped<T>(points, valid, k, leaf, entries))
}

}  // namespace

// lieax._threads' setting (0: one thread per core), called through ctypes.
LIEAX_EXPORT void LieaxSetThreads(int threads) { g_threads.store(threads); }
LIEAX_EXPORT int LieaxThreads() { return g_threads.load(); }

#define LIEAX_TREE_ARGS                 \
  .Arg<ffi::AnyBuffer>()                \
      .Arg<ffi::AnyBuffer>()            \
      .Arg<ffi::AnyBuffer>()            \
      .Arg<ffi::AnyBuffer>()            \
      .Arg<ffi::AnyBuffer>()

LIEAX_FFI_HANDLER(LieaxKdtreeBuild, BuildImpl,
                  ffi::Ffi::Bind()
                      .Arg<ffi::AnyBuffer>()
                      .Arg<ffi::Buffer<ffi::PRED>>()
                      .Attr<int64_t>("leaf_size")
                      .Ret<ffi::Buffer<ffi::S32>>()
                      .Ret<ffi::AnyBuffer>()
                      .Ret<ffi::Buffer<ffi::S32>>()
                      .Ret<ffi::AnyBuffer>()
                      .Ret<ffi::AnyBuffer>());

LIEAX_FFI_HANDLER(LieaxKdtreeNearest, NearestImpl,
                  ffi::Ffi::Bind() LIEAX_TREE_ARGS.Arg<ffi::AnyBuffer>()
                      .Arg<ffi::AnyBuffer>()
                      .Arg<ffi::Buffer<ffi::PRED>>()
                      .Ret<ffi::Buffer<ffi::S32>>()
                      .Ret<ffi::AnyBuffer>());

LIEAX_FFI_HANDLER(LieaxKdtreeTrack, TrackImpl,
                  ffi::Ffi::Bind() LIEAX_TREE_ARGS.Arg<ffi::AnyBuffer>()
                      .Arg<ffi::AnyBuffer>()
                      .Arg<ffi::Buffer<ffi::PRED>>()
                      .Arg<ffi::Buffer<ffi::PRED>>()
                      .Ret<ffi::Buffer<ffi::S32>>()
                      .Ret<ffi::AnyBuffer>());

LIEAX_FFI_HANDLER(LieaxKdtreeSpacing, SpacingImpl,
                  ffi::Ffi::Bind() LIEAX_TREE_ARGS.Ret<ffi::AnyBuffer>());

LIEAX_FFI_HANDLER(LieaxKdtreeNeighbours, NeighboursImpl,
                  ffi::Ffi::Bind()
                      .Arg<ffi::AnyBuffer>()
                      .Arg<ffi::Buffer<ffi::PRED>>()
                      .Attr<int64_t>("leaf_size")
                      .Ret<ffi::Buffer<ffi::S32>>());

LIEAX_FFI_HANDLER(LieaxKdtreeCovariances, CovariancesImpl,
                  ffi::Ffi::Bind()
                      .Arg<ffi::AnyBuffer>()
                      .Arg<ffi::Buffer<ffi::PRED>>()
                      .Attr<int64_t>("k")
                      .Attr<int64_t>("leaf_size")
                      .Ret<ffi::AnyBuffer>());
