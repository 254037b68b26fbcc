#include "cscam/cspace/certificates.hpp"

#include <algorithm>

namespace cscam::cspace {

void CertificateStore::reserve() {
  if (!grid_.empty()) return;
  const auto n1 = static_cast<std::size_t>(sp_.i1_max() - sp_.i1_min()) + 1;
  const auto n2 = static_cast<std::size_t>(sp_.i2_max() - sp_.i2_min()) + 1;
  grid_.resize(n1 * n2);
}

CertificateStore::Entry* CertificateStore::entry(int i1, int i2) {
  if (i1 < sp_.i1_min() || i1 > sp_.i1_max() || i2 < sp_.i2_min() || i2 > sp_.i2_max() || grid_.empty()) return nullptr;
  const auto n1 = static_cast<std::size_t>(sp_.i1_max() - sp_.i1_min()) + 1;
  return &grid_[static_cast<std::size_t>(i2 - sp_.i2_min()) * n1 + static_cast<std::size_t>(i1 - sp_.i1_min())];
}

void CertificateStore::evaluate(const kin::Posed& cl, Cell& cell, geom::QueryWorkspace& ws, Counters& c) {
  Entry* e = sp_.options().cone_rad > 0 ? entry(cell.i1, cell.i2) : nullptr;
  // The entry must describe this very cell (a grid cell's values are its indices times the resolution).
  if (!e || cell.r1 != sp_.r1_of(cell.i1) || cell.r2 != sp_.r2_of(cell.i2)) {
    sp_.evaluate(cl, cell, ws, c);
    return;
  }
  if (cell.status != Status::Unknown) {
    ++c.cache_hits;
    return;
  }
  if (e->room == Room::Tight) {
    sp_.evaluate(cl, cell, ws, c, nullptr, &e->hit);
    if (cell.status != Status::Feasible) e->room = Room::Unknown;
    return;
  }
  if (e->room == Room::Unknown) e->cert.probe_mm = 1.0;
  if (e->room == Room::Unknown && !e->cert.valid) {
    // (A cell that collided lands here each time: its hit certificate spares the queries.)
    sp_.evaluate(cl, cell, ws, c, nullptr, &e->hit);
    if (cell.status == Status::Feasible) e->room = Room::Free;
    return;
  }
  // Covered by the certificate, or free before: reuse, or probe with the margin (Space::evaluate decides).
  sp_.evaluate(cl, cell, ws, c, &e->cert, &e->hit);
  if (cell.status != Status::Feasible) {
    e->room = Room::Unknown;
  } else if (!e->cert.valid) {
    // Free, but not with this margin: ask for half next time; below the smallest useful margin, no more probes
    // while it stays free (a probe that fails costs a second query).
    e->cert.probe_mm *= 0.5;
    e->room = e->cert.probe_mm < kMinProbeMm ? Room::Tight : Room::Free;
  } else {
    e->room = Room::Free;
    e->cert.probe_mm = std::min(1.0, 2.0 * e->cert.probe_mm);  // room again: certify further ahead next time
  }
}

}  // namespace cscam::cspace
