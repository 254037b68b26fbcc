#pragma once
/// @file
/// Clearance certificates kept per grid cell across the points of a segment (issue 11, part 3). A cell proven
/// free at one point with an extra margin m stays free at the next points while its tool has moved less than m
/// (same rotaries: same tool axis and machine-body poses), so a search that revisits the same cells point after
/// point (the shortest-path beam) needs a collision query only every m of travel per cell.
#include <cstdint>
#include <vector>

#include "cscam/cspace/cspace.hpp"

namespace cscam::cspace {

/// One certificate per cell of a Space's grid, dense (allocated on first use). Not thread-safe as a whole, but
/// evaluate() touches only the entry of its cell: calls on distinct cells may run in parallel.
class CertificateStore {
 public:
  explicit CertificateStore(const Space& space) : sp_(space) {}

  /// Space::evaluate with the cell's certificate: a pose the certificate covers costs no query; a cell that was
  /// free at its previous evaluation is probed with the margin (one query that, when free, certifies the next
  /// points); a cell whose margin probe failed is checked plainly from then on (no second query per point).
  /// Grid cells only (exact-orientation cells are evaluated plainly).
  void evaluate(const kin::Posed& cl_pose, Cell& cell, geom::QueryWorkspace& ws, Counters& c);

  /// Allocates the grid (call once before evaluating in parallel).
  void reserve();

  /// Smallest probe margin worth a query, mm: at 1/16 mm a certificate still covers a few points of a fine path.
  static constexpr double kMinProbeMm = 1.0 / 16.0;

 private:
  enum class Room : std::uint8_t { Unknown, Free, Tight };
  struct Entry {
    Certificate cert;
    HitCertificate hit;
    Room room = Room::Unknown;
  };
  Entry* entry(int i1, int i2);
  const Space& sp_;
  std::vector<Entry> grid_;
};

}  // namespace cscam::cspace
