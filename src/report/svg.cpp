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
  const int w = std::max(0, sp.width()), h = std::max(0, sp.height());
  const std::size_t np = sp.panels.size();
  const int cols = static_cast<int>(std::min<std::size_t>(4, std::max<std::size_t>(1, np)));
  const int rows = static_cast<int>((np + static_cast<std::size_t>(cols) - 1) / static_cast<std::size_t>(cols));
  // Panels of pw x ph px, a label above each, ticks left of and below it.
  const double pw = 200, ph = 150, cw = pw / std::max(1, w), ch = ph / std::max(1, h);
  const double ml = 60, mt = 50, gap_x = 60, gap_y = 62, legend_w = 230;
  const double W = ml + cols * (pw + gap_x) + legend_w, H = mt + rows * (ph + gap_y) + 60;
  std::string s = fmt::format(
      "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{:.0f}\" height=\"{:.0f}\" font-family=\"sans-serif\" "
      "font-size=\"11\">\n<rect width=\"100%\" height=\"100%\" fill=\"white\"/>\n"
      "<text x=\"{}\" y=\"24\" font-size=\"15\">{}</text>\n",
      W, H, ml, title);
  const double res1 = sp.resolution1_rad, res2 = sp.resolution2_rad;
  auto X = [&](double r1) { return (r1 / res1 - sp.i1_min + 0.5) * cw; };
  auto Y = [&](double r2) { return ph - (r2 / res2 - sp.i2_min + 0.5) * ch; };
  // The whole path once, reused in every panel.
  std::string path_pts;
  for (const auto& [r1, r2] : sp.path) path_pts += fmt::format("{:.1f},{:.1f} ", X(r1), Y(r2));
  if (!path_pts.empty()) path_pts.pop_back();
  const cspace::Status shown[] = {cspace::Status::Feasible, cspace::Status::Stroke, cspace::Status::Collision};
  std::size_t in_cone = 0, counts[5] = {0, 0, 0, 0, 0}, chosen_feasible = 0;
  for (std::size_t i = 0; i < np; ++i) {
    const auto& p = sp.panels[i];
    const double x0 = ml + static_cast<double>(static_cast<int>(i) % cols) * (pw + gap_x);
    const double y0 = mt + 18 + static_cast<double>(static_cast<int>(i) / cols) * (ph + gap_y);
    s += fmt::format("<g class=\"panel\" data-line=\"{}\" data-point=\"{}\" transform=\"translate({:.1f},{:.1f})\">\n",
                     p.line, p.point + 1, x0, y0);
    s += fmt::format("<text x=\"0\" y=\"-5\">CL line {} ({}/{})</text>\n", p.line, p.point + 1, sp.points);
    // Outside the cone is the background; the other cells as runs along the rows, one path per status, in cell
    // units (row 0 at the bottom).
    s += fmt::format("<rect width=\"{:.1f}\" height=\"{:.1f}\" fill=\"{}\"/>\n", pw, ph,
                     colour(cspace::Status::Orientation));
    s += fmt::format("<g transform=\"matrix({:.4f} 0 0 {:.4f} 0 {:.1f})\" shape-rendering=\"crispEdges\">\n", cw, -ch,
                     ph);
    for (cspace::Status st : shown) {
      std::string d;
      for (int b = 0; b < h; ++b)
        for (int a = 0; a < w;) {
          if (p.status[static_cast<std::size_t>(b * w + a)] != st) {
            ++a;
            continue;
          }
          int e = a + 1;
          while (e < w && p.status[static_cast<std::size_t>(b * w + e)] == st) ++e;
          d += fmt::format("M{} {}h{}v1h-{}z", a, b, e - a, e - a);
          a = e;
        }
      if (!d.empty())
        s += fmt::format("<path class=\"{}\" fill=\"{}\" d=\"{}\"/>\n", cspace::to_string(st), colour(st), d);
    }
    s += "</g>\n";
    for (cspace::Status st : p.status) {
      if (st == cspace::Status::Orientation) continue;
      ++in_cone;
      ++counts[static_cast<int>(st)];
    }
    if (!path_pts.empty())
      s += fmt::format("<polyline fill=\"none\" stroke=\"#1f3a93\" stroke-width=\"1.2\" points=\"{}\"/>\n", path_pts);
    // The plan's cell at this point, outlined, in the colour of its status.
    const int ca = sp.i1_of(p.chosen.first) - sp.i1_min, cb = sp.i2_of(p.chosen.second) - sp.i2_min;
    if (p.chosen_status == cspace::Status::Feasible) ++chosen_feasible;
    s += fmt::format(
        "<rect class=\"chosen\" data-status=\"{}\" data-cell=\"{} {}\" x=\"{:.1f}\" y=\"{:.1f}\" width=\"{:.1f}\" "
        "height=\"{:.1f}\" fill=\"{}\" stroke=\"black\" stroke-width=\"1.5\"/>\n",
        cspace::to_string(p.chosen_status), ca, cb, ca * cw, ph - (cb + 1) * ch, std::max(cw, 3.0), std::max(ch, 3.0),
        colour(p.chosen_status));
    s += fmt::format("<rect width=\"{:.1f}\" height=\"{:.1f}\" fill=\"none\" stroke=\"black\"/>\n", pw, ph);
    // Ticks: the window's ends, degrees.
    s += fmt::format("<text x=\"0\" y=\"{:.1f}\">{:.1f}</text>", ph + 13, rad2deg(sp.i1_min * res1));
    s += fmt::format("<text x=\"{:.1f}\" y=\"{:.1f}\" text-anchor=\"end\">{:.1f}</text>", pw, ph + 13,
                     rad2deg(sp.i1_max * res1));
    s += fmt::format("<text x=\"{:.1f}\" y=\"{:.1f}\" text-anchor=\"middle\">{}</text>\n", pw / 2, ph + 13, n1);
    s += fmt::format("<text x=\"-4\" y=\"{:.1f}\" text-anchor=\"end\">{:.1f}</text>", ph, rad2deg(sp.i2_min * res2));
    s += fmt::format("<text x=\"-4\" y=\"9\" text-anchor=\"end\">{:.1f}</text>", rad2deg(sp.i2_max * res2));
    s += fmt::format("<text x=\"-4\" y=\"{:.1f}\" text-anchor=\"end\">{}</text>\n</g>\n", ph / 2, n2);
  }
  // Legend.
  const double lx = ml + cols * (pw + gap_x), ly = mt + 18;
  const char* labels[] = {"feasible", "outside stroke (limit)", "colliding", "outside the cone"};
  const cspace::Status sts[] = {cspace::Status::Feasible, cspace::Status::Stroke, cspace::Status::Collision,
                                cspace::Status::Orientation};
  for (int i = 0; i < 4; ++i)
    s += fmt::format(
        "<rect x=\"{}\" y=\"{}\" width=\"14\" height=\"14\" fill=\"{}\" stroke=\"#999\"/><text x=\"{}\" "
        "y=\"{}\">{}</text>\n",
        lx, ly + i * 20, colour(sts[i]), lx + 20, ly + i * 20 + 11, labels[i]);
  s += fmt::format(
      "<line x1=\"{}\" y1=\"{}\" x2=\"{}\" y2=\"{}\" stroke=\"#1f3a93\" stroke-width=\"2\"/><text x=\"{}\" "
      "y=\"{}\">planned path (all points)</text>\n",
      lx, ly + 87, lx + 14, ly + 87, lx + 20, ly + 91);
  s += fmt::format(
      "<rect x=\"{}\" y=\"{}\" width=\"14\" height=\"14\" fill=\"none\" stroke=\"black\" stroke-width=\"1.5\"/><text "
      "x=\"{}\" y=\"{}\">planned cell at this point</text>\n",
      lx, ly + 100, lx + 20, ly + 111);
  s += fmt::format("<text x=\"{}\" y=\"{}\">cells {:.2f} x {:.2f} deg; cone {:.2f} deg</text>\n", lx, ly + 140,
                   rad2deg(res1), rad2deg(res2), rad2deg(sp.cone_rad));
  auto pct = [&](std::size_t n) {
    return in_cone ? 100.0 * static_cast<double>(n) / static_cast<double>(in_cone) : 0.0;
  };
  s += fmt::format(
      "<text class=\"summary\" x=\"{}\" y=\"{:.0f}\">{} of {} CL points shown (CL lines {}-{}); cells in the cone: "
      "{:.0f} % feasible, {:.0f} % outside stroke, {:.0f} % colliding;<tspan x=\"{}\" dy=\"16\">the planned cell is "
      "feasible at {} of {} shown points</tspan></text>\n",
      ml, H - 36, np, sp.points, sp.first_line, sp.last_line, pct(counts[static_cast<int>(cspace::Status::Feasible)]),
      pct(counts[static_cast<int>(cspace::Status::Stroke)]), pct(counts[static_cast<int>(cspace::Status::Collision)]),
      ml, chosen_feasible, np);
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
