// scandyn/scan/tree_plan.hpp: how a tree is cut for parallel root-path and subtree scans.
//
// Bodies are in depth-first preorder, so every maximal chain run appears as a
// contiguous range: a segment [begin, end) where parent[i] == i - 1 inside it.
// Segments form a tree of their own; its depth is the segment's level. A scan
// processes levels in order (root-path prefix) or in reverse (subtree suffix);
// segments of one level are independent. Long segments are cut into pieces that
// are scanned in parallel and joined by a short serial pass over piece carries.
#pragma once

#include <vector>

#include "scandyn/config.hpp"

namespace scandyn {

struct TreeScanPlan {
  struct Piece {
    Index begin, end;  // node range [begin, end), inside one segment
    Index segment;     // owning segment
    bool first;        // first (root-most) piece of its segment
    bool last;         // last (leaf-most) piece of its segment
  };

  Index n = 0;                               // number of nodes
  std::vector<Index> parent;                 // (n) parent node, -1 at a root
  std::vector<Index> seg_begin, seg_end;     // (nseg) node ranges
  std::vector<Index> seg_parent_node;        // (nseg) parent of seg_begin, -1 at a root
  std::vector<Index> child_segs;             // segments grouped by the segment holding their parent node
  std::vector<Index> child_segs_begin;       // (nseg + 1) offsets into child_segs
  std::vector<Piece> pieces;                 // all pieces, grouped by level
  std::vector<Index> level_begin;            // (nlevels + 1) offsets into pieces
  bool has_split_segments = false;           // some segment has more than one piece

  Index num_segments() const { return static_cast<Index>(seg_begin.size()); }
  Index num_levels() const { return static_cast<Index>(level_begin.size()) - 1; }
};

// Builds the plan for a preorder parent array. Segments longer than max_piece
// nodes are cut into pieces of at most max_piece nodes.
TreeScanPlan make_tree_scan_plan(const std::vector<Index>& parent, Index max_piece);

// A max_piece giving each of `threads` threads a few pieces of a chain of n nodes,
// and no cutting at all for small n.
Index default_max_piece(Index n, int threads);

}  // namespace scandyn
