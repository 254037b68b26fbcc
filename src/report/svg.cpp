#include "cscam/report/svg.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>

#include "cscam/core/units.hpp"

namespace cscam::report {

namespace {
const char* colour(cspace::Status s) {
  switch (s) {
    case cspace::Status::Feasible:
      return "#5cb85c";
    case cspace::Status::Orientation:
      return "#e6e6e6";
    case cspace::Status::Stroke:
      return "#f0ad4e";
    case cspace::Status::Collision:
      return "#d9534f";
    default:
      return "#ffffff";
  }
}
}  // namespace

std::string cspace_svg(const plan::SegmentSpace& sp, const std::string& n1, const std::string& n2,
                       const std::string& title) {
  const int c1 = sp.i1_max - sp.i1_min + 1, c2 = sp.i2_max - sp.i2_min + 1;
  const double W = 820, H = 520, ml = 70, mb = 60, mt = 50, mr = 230;
  const double cw = (W - ml - mr) / std::max(1, c1), ch = (H - mt - mb) / std::max(1, c2);
  std::string s = fmt::format(
      "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{}\" height=\"{}\" font-family=\"sans-serif\" "
      "font-size=\"12\">\n"
      "<rect width=\"100%\" height=\"100%\" fill=\"white\"/>\n<text x=\"{}\" y=\"25\" font-size=\"15\">{}</text>\n",
      W, H, ml, title);
  auto X = [&](double r1) { return ml + (r1 / sp.resolution_rad - sp.i1_min + 0.5) * cw; };
  auto Y = [&](double r2) { return H - mb - (r2 / sp.resolution_rad - sp.i2_min + 0.5) * ch; };
  // One rectangle per run of equal cells along a row (the same picture, a fraction of the file).
  for (int b = 0; b < c2; ++b)
    for (int a = 0; a < c1;) {
      const cspace::Status st = sp.status[static_cast<size_t>(b * c1 + a)];
      int e = a + 1;
      while (e < c1 && sp.status[static_cast<size_t>(b * c1 + e)] == st) ++e;
      s += fmt::format("<rect x=\"{:.2f}\" y=\"{:.2f}\" width=\"{:.2f}\" height=\"{:.2f}\" fill=\"{}\"/>\n",
                       ml + a * cw, H - mb - (b + 1) * ch, (e - a) * cw + 0.05, ch + 0.05, colour(st));
      a = e;
    }
  if (!sp.path.empty()) {
    s += "<polyline fill=\"none\" stroke=\"#1f3a93\" stroke-width=\"2\" points=\"";
    for (const auto& [r1, r2] : sp.path) s += fmt::format("{:.2f},{:.2f} ", X(r1), Y(r2));
    s += "\"/>\n";
    s += fmt::format("<circle cx=\"{:.2f}\" cy=\"{:.2f}\" r=\"4\" fill=\"#1f3a93\"/>\n", X(sp.path.front().first),
                     Y(sp.path.front().second));
  }
  // Axes and ticks (degrees).
  s += fmt::format("<rect x=\"{}\" y=\"{}\" width=\"{}\" height=\"{}\" fill=\"none\" stroke=\"black\"/>\n", ml, mt,
                   W - ml - mr, H - mt - mb);
  for (int t = 0; t <= 4; ++t) {
    const double r1 = (sp.i1_min + (c1 - 1) * t / 4.0) * sp.resolution_rad;
    const double r2 = (sp.i2_min + (c2 - 1) * t / 4.0) * sp.resolution_rad;
    s += fmt::format("<text x=\"{:.1f}\" y=\"{}\" text-anchor=\"middle\">{:.1f}</text>\n", X(r1), H - mb + 18,
                     rad2deg(r1));
    s += fmt::format("<text x=\"{}\" y=\"{:.1f}\" text-anchor=\"end\">{:.1f}</text>\n", ml - 6, Y(r2) + 4, rad2deg(r2));
  }
  s += fmt::format("<text x=\"{}\" y=\"{}\" text-anchor=\"middle\">{} (deg)</text>\n", (ml + W - mr) / 2, H - 15, n1);
  s += fmt::format("<text x=\"18\" y=\"{}\" transform=\"rotate(-90 18 {})\" text-anchor=\"middle\">{} (deg)</text>\n",
                   (mt + H - mb) / 2, (mt + H - mb) / 2, n2);
  const char* labels[] = {"feasible at every point", "outside the cone (orientation)", "stroke limit", "collision",
                          "planned path"};
  const cspace::Status sts[] = {cspace::Status::Feasible, cspace::Status::Orientation, cspace::Status::Stroke,
                                cspace::Status::Collision};
  for (int i = 0; i < 5; ++i) {
    const double y = mt + 10 + i * 22;
    if (i < 4)
      s += fmt::format("<rect x=\"{}\" y=\"{}\" width=\"14\" height=\"14\" fill=\"{}\" stroke=\"#999\"/>\n",
                       W - mr + 12, y, colour(sts[i]));
    else
      s += fmt::format("<line x1=\"{}\" y1=\"{}\" x2=\"{}\" y2=\"{}\" stroke=\"#1f3a93\" stroke-width=\"2\"/>\n",
                       W - mr + 12, y + 7, W - mr + 26, y + 7);
    s += fmt::format("<text x=\"{}\" y=\"{}\">{}</text>\n", W - mr + 32, y + 12, labels[i]);
  }
  s += "</svg>\n";
  return s;
}

std::string axis_plot_svg(const std::vector<std::vector<kin::Axes>>& paths, const std::vector<std::string>& labels,
                          const std::array<int, 2>& rot, const std::array<std::string, 2>& names, std::size_t first,
                          std::size_t last, const std::string& title) {
  const double W = 760, Hp = 230, ml = 70, mr = 150, mt = 40;
  const double H = mt + 2 * Hp + 20;
  const char* cols[] = {"#d9534f", "#1f3a93", "#5cb85c", "#f0ad4e"};
  std::string s = fmt::format(
      "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{}\" height=\"{}\" font-family=\"sans-serif\" "
      "font-size=\"12\">\n"
      "<rect width=\"100%\" height=\"100%\" fill=\"white\"/>\n<text x=\"{}\" y=\"25\" font-size=\"15\">{}</text>\n",
      W, H, ml, title);
  const std::size_t n = last >= first ? last - first + 1 : 0;
  for (int a = 0; a < 2; ++a) {
    const double top = mt + a * Hp, bottom = top + Hp - 40;
    double lo = 1e300, hi = -1e300;
    for (const auto& p : paths)
      for (std::size_t i = first; i <= last && i < p.size(); ++i) {
        lo = std::min(lo, rad2deg(p[i][rot[static_cast<size_t>(a)]]));
        hi = std::max(hi, rad2deg(p[i][rot[static_cast<size_t>(a)]]));
      }
    if (!(hi > lo)) {
      lo -= 1;
      hi += 1;
    }
    auto X = [&](std::size_t i) { return ml + (W - ml - mr) * (n > 1 ? double(i - first) / double(n - 1) : 0.5); };
    auto Y = [&](double v) { return bottom - (bottom - top) * (v - lo) / (hi - lo); };
    s += fmt::format("<rect x=\"{}\" y=\"{}\" width=\"{}\" height=\"{}\" fill=\"none\" stroke=\"black\"/>\n", ml, top,
                     W - ml - mr, bottom - top);
    s += fmt::format("<text x=\"{}\" y=\"{:.1f}\" text-anchor=\"end\">{:.1f}</text>\n", ml - 6, top + 4, hi);
    s += fmt::format("<text x=\"{}\" y=\"{:.1f}\" text-anchor=\"end\">{:.1f}</text>\n", ml - 6, bottom + 4, lo);
    s += fmt::format("<text x=\"14\" y=\"{:.1f}\">{}</text>\n", (top + bottom) / 2, names[static_cast<size_t>(a)]);
    for (std::size_t k = 0; k < paths.size(); ++k) {
      s += fmt::format("<polyline fill=\"none\" stroke=\"{}\" stroke-width=\"1.5\" points=\"", cols[k % 4]);
      for (std::size_t i = first; i <= last && i < paths[k].size(); ++i)
        s += fmt::format("{:.1f},{:.1f} ", X(i), Y(rad2deg(paths[k][i][rot[static_cast<size_t>(a)]])));
      s += "\"/>\n";
    }
  }
  for (std::size_t k = 0; k < labels.size(); ++k)
    s += fmt::format(
        "<line x1=\"{}\" y1=\"{}\" x2=\"{}\" y2=\"{}\" stroke=\"{}\" stroke-width=\"2\"/><text x=\"{}\" "
        "y=\"{}\">{}</text>\n",
        W - mr + 10, mt + 10 + 20 * k, W - mr + 30, mt + 10 + 20 * k, cols[k % 4], W - mr + 36, mt + 14 + 20 * k,
        labels[k]);
  s += fmt::format("<text x=\"{}\" y=\"{}\" text-anchor=\"middle\">CL point</text>\n", (ml + W - mr) / 2, H - 8);
  s += "</svg>\n";
  return s;
}

}  // namespace cscam::report
