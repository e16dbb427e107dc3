// Cutting a preorder tree into segments, levels and pieces for parallel scans.
#include "scandyn/scan/tree_plan.hpp"

#include <algorithm>

namespace scandyn {

TreeScanPlan make_tree_scan_plan(const std::vector<Index>& parent, Index max_piece) {
  TreeScanPlan p;
  p.n = static_cast<Index>(parent.size());
  p.parent = parent;
  if (max_piece < 1) max_piece = 1;
  // segments: maximal runs with parent[i] == i - 1
  std::vector<Index> seg_of(parent.size());
  for (Index i = 0; i < p.n; ++i) {
    if (i == 0 || parent[i] != i - 1) {
      if (i > 0) p.seg_end.push_back(i);
      p.seg_begin.push_back(i);
      p.seg_parent_node.push_back(parent[i]);
    }
    seg_of[i] = p.num_segments() - 1;
  }
  if (p.n > 0) p.seg_end.push_back(p.n);
  const Index nseg = p.num_segments();

  // segment levels; parents come first in preorder
  std::vector<Index> level(nseg, 0), parent_seg(nseg, -1);
  Index nlevels = nseg > 0 ? 1 : 0;
  for (Index s = 0; s < nseg; ++s) {
    const Index pn = p.seg_parent_node[s];
    if (pn >= 0) {
      parent_seg[s] = seg_of[pn];
      level[s] = level[parent_seg[s]] + 1;
      nlevels = std::max(nlevels, level[s] + 1);
    }
  }

  // child segments grouped by parent segment (CSR)
  p.child_segs_begin.assign(nseg + 1, 0);
  for (Index s = 0; s < nseg; ++s)
    if (parent_seg[s] >= 0) ++p.child_segs_begin[parent_seg[s] + 1];
  for (Index s = 0; s < nseg; ++s) p.child_segs_begin[s + 1] += p.child_segs_begin[s];
  p.child_segs.resize(p.child_segs_begin[nseg]);
  std::vector<Index> fill(p.child_segs_begin.begin(), p.child_segs_begin.end() - 1);
  for (Index s = 0; s < nseg; ++s)
    if (parent_seg[s] >= 0) p.child_segs[fill[parent_seg[s]]++] = s;

  // pieces, grouped by level
  std::vector<Index> by_level_count(nlevels + 1, 0);
  for (Index s = 0; s < nseg; ++s) ++by_level_count[level[s] + 1];
  for (Index l = 0; l < nlevels; ++l) by_level_count[l + 1] += by_level_count[l];
  std::vector<Index> segs_by_level(nseg);
  std::vector<Index> pos(by_level_count.begin(), by_level_count.end() - 1);
  for (Index s = 0; s < nseg; ++s) segs_by_level[pos[level[s]]++] = s;
  p.level_begin.push_back(0);
  for (Index l = 0; l < nlevels; ++l) {
    for (Index k = by_level_count[l]; k < by_level_count[l + 1]; ++k) {
      const Index s = segs_by_level[k];
      const Index b = p.seg_begin[s], e = p.seg_end[s];
      const Index count = (e - b + max_piece - 1) / max_piece;
      const Index len = (e - b + count - 1) / count;  // even split
      for (Index c = 0; c < count; ++c) {
        const Index pb = b + c * len, pe = std::min(e, pb + len);
        p.pieces.push_back({pb, pe, s, c == 0, c == count - 1});
      }
      if (count > 1) p.has_split_segments = true;
    }
    p.level_begin.push_back(static_cast<Index>(p.pieces.size()));
  }
  return p;
}

Index default_max_piece(Index n, int threads) {
  if (threads <= 1 || n < 4096) return std::max<Index>(n, 1);
  const Index per = (n + 4 * threads - 1) / (4 * threads);
  return std::max<Index>(per, 1024);
}

}  // namespace scandyn
