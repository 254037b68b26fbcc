#include "cscam/geom/mesh.hpp"

#include <assimp/postprocess.h>
#include <assimp/scene.h>
#include <fmt/format.h>
#include <poll.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <assimp/Importer.hpp>
#include <bit>
#include <cctype>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <unordered_map>
#include <vector>

#include "cscam/core/atomic_file.hpp"
#include "cscam/core/error.hpp"

namespace cscam::geom {

namespace {

std::string fmt_point(const Eigen::Vector3d& p) { return fmt::format("({:.6g}, {:.6g}, {:.6g})", p.x(), p.y(), p.z()); }

std::uint64_t edge_key(int a, int b) {
  return (static_cast<std::uint64_t>(static_cast<std::uint32_t>(a)) << 32) | static_cast<std::uint32_t>(b);
}

/// Welds vertices closer than `tol` (hash grid with cell size tol, 27-cell neighbourhood) and
/// re-indexes the triangles; drops triangles that became degenerate. Returns the number dropped.
std::size_t weld(Mesh& mesh, double tol) {
  if (mesh.vertices_mm.empty() || !(tol > 0.0)) return 0;
  struct KeyHash {
    std::size_t operator()(const std::array<std::int64_t, 3>& k) const {
      std::uint64_t h = static_cast<std::uint64_t>(k[0]) * 0x9E3779B97F4A7C15ull;
      h ^= static_cast<std::uint64_t>(k[1]) * 0xC2B2AE3D27D4EB4Full + (h << 6) + (h >> 2);
      h ^= static_cast<std::uint64_t>(k[2]) * 0x165667B19E3779F9ull + (h << 6) + (h >> 2);
      return static_cast<std::size_t>(h);
    }
  };
  std::unordered_map<std::array<std::int64_t, 3>, std::vector<int>, KeyHash> grid;
  grid.reserve(mesh.vertices_mm.size());
  std::vector<Eigen::Vector3d> out;
  out.reserve(mesh.vertices_mm.size());
  std::vector<int> remap(mesh.vertices_mm.size());
  const double tol2 = tol * tol;
  for (std::size_t i = 0; i < mesh.vertices_mm.size(); ++i) {
    const Eigen::Vector3d& p = mesh.vertices_mm[i];
    const std::array<std::int64_t, 3> key{static_cast<std::int64_t>(std::floor(p.x() / tol)),
                                          static_cast<std::int64_t>(std::floor(p.y() / tol)),
                                          static_cast<std::int64_t>(std::floor(p.z() / tol))};
    int found = -1;
    for (int dx = -1; dx <= 1 && found < 0; ++dx)
      for (int dy = -1; dy <= 1 && found < 0; ++dy)
        for (int dz = -1; dz <= 1 && found < 0; ++dz) {
          auto it = grid.find({key[0] + dx, key[1] + dy, key[2] + dz});
          if (it == grid.end()) continue;
          for (int j : it->second)
            if ((out[static_cast<std::size_t>(j)] - p).squaredNorm() <= tol2) {
              found = j;
              break;
            }
        }
    if (found < 0) {
      found = static_cast<int>(out.size());
      out.push_back(p);
      grid[key].push_back(found);
    }
    remap[i] = found;
  }
  std::vector<Eigen::Vector3i> tris;
  tris.reserve(mesh.triangles.size());
  std::size_t dropped = 0;
  for (const auto& t : mesh.triangles) {
    const Eigen::Vector3i u(remap[static_cast<std::size_t>(t[0])], remap[static_cast<std::size_t>(t[1])],
                            remap[static_cast<std::size_t>(t[2])]);
    if (u[0] == u[1] || u[1] == u[2] || u[0] == u[2]) {
      ++dropped;
      continue;
    }
    tris.push_back(u);
  }
  mesh.vertices_mm = std::move(out);
  mesh.triangles = std::move(tris);
  return dropped;
}

void collect(const aiScene* scene, const aiNode* node, const aiMatrix4x4& parent, double scale, Mesh& mesh) {
  const aiMatrix4x4 T = parent * node->mTransformation;
  for (unsigned k = 0; k < node->mNumMeshes; ++k) {
    const aiMesh* m = scene->mMeshes[node->mMeshes[k]];
    const int base = static_cast<int>(mesh.vertices_mm.size());
    for (unsigned v = 0; v < m->mNumVertices; ++v) {
      const aiVector3D p = T * m->mVertices[v];
      mesh.vertices_mm.emplace_back(scale * p.x, scale * p.y, scale * p.z);
    }
    for (unsigned f = 0; f < m->mNumFaces; ++f) {
      const aiFace& face = m->mFaces[f];
      if (face.mNumIndices != 3) continue;  // points and lines (polygons were triangulated)
      mesh.triangles.emplace_back(base + static_cast<int>(face.mIndices[0]), base + static_cast<int>(face.mIndices[1]),
                                  base + static_cast<int>(face.mIndices[2]));
    }
  }
  for (unsigned c = 0; c < node->mNumChildren; ++c) collect(scene, node->mChildren[c], T, scale, mesh);
}

}  // namespace

Eigen::AlignedBox3d Mesh::bounding_box() const {
  Eigen::AlignedBox3d box;  // empty
  for (const auto& v : vertices_mm) box.extend(v);
  return box;
}

bool Mesh::is_closed(std::string* why) const {
  auto fail = [&](std::string msg) {
    if (why) *why = std::move(msg);
    return false;
  };
  if (triangles.empty()) return fail("mesh has no triangles");
  const int nv = static_cast<int>(vertices_mm.size());
  std::size_t degenerate = 0;
  std::unordered_map<std::uint64_t, int> directed;
  directed.reserve(triangles.size() * 3);
  for (std::size_t t = 0; t < triangles.size(); ++t) {
    const auto& tri = triangles[t];
    for (int k = 0; k < 3; ++k)
      if (tri[k] < 0 || tri[k] >= nv)
        return fail(fmt::format("triangle {} has vertex index {} out of range [0, {})", t, tri[k], nv));
    if (tri[0] == tri[1] || tri[1] == tri[2] || tri[0] == tri[2]) {
      ++degenerate;
      continue;
    }
    for (int k = 0; k < 3; ++k) ++directed[edge_key(tri[k], tri[(k + 1) % 3])];
  }
  std::size_t boundary = 0, non_manifold = 0, flipped = 0;
  std::string example;
  auto note = [&](int a, int b, const char* what) {
    if (example.empty())
      example = fmt::format("; e.g. {} edge {} - {}", what, fmt_point(vertices_mm[static_cast<std::size_t>(a)]),
                            fmt_point(vertices_mm[static_cast<std::size_t>(b)]));
  };
  for (const auto& [key, count] : directed) {
    const int a = static_cast<int>(key >> 32), b = static_cast<int>(key & 0xffffffffu);
    const auto rev = directed.find(edge_key(b, a));
    const int rcount = rev == directed.end() ? 0 : rev->second;
    if (rcount > 0 && a > b) continue;  // the pair is handled once, from its smaller first index
    const int total = count + rcount;
    if (total == 1) {
      ++boundary;
      note(a, b, "boundary");
    } else if (total > 2) {
      ++non_manifold;
      note(a, b, "non-manifold");
    } else if (count != rcount) {
      ++flipped;
      note(a, b, "inconsistently oriented");
    }
  }
  if (boundary == 0 && non_manifold == 0 && flipped == 0 && degenerate == 0) return true;
  return fail(fmt::format(
      "mesh is not closed: {} boundary edge(s), {} non-manifold edge(s), {} inconsistently oriented edge(s), "
      "{} degenerate triangle(s){}",
      boundary, non_manifold, flipped, degenerate, example));
}

double Mesh::signed_volume_mm3() const {
  if (vertices_mm.empty()) return 0.0;
  const Eigen::Vector3d o = bounding_box().center();  // better conditioned than the origin
  double six_v = 0.0;
  for (const auto& t : triangles) {
    const Eigen::Vector3d a = vertices_mm[static_cast<std::size_t>(t[0])] - o;
    const Eigen::Vector3d b = vertices_mm[static_cast<std::size_t>(t[1])] - o;
    const Eigen::Vector3d c = vertices_mm[static_cast<std::size_t>(t[2])] - o;
    six_v += a.dot(b.cross(c));
  }
  return six_v / 6.0;
}

double Mesh::area_mm2() const {
  double a2 = 0.0;
  for (const auto& t : triangles) {
    const Eigen::Vector3d& a = vertices_mm[static_cast<std::size_t>(t[0])];
    a2 +=
        (vertices_mm[static_cast<std::size_t>(t[1])] - a).cross(vertices_mm[static_cast<std::size_t>(t[2])] - a).norm();
  }
  return 0.5 * a2;
}

Mesh box_mesh(const Eigen::Vector3d& lo, const Eigen::Vector3d& hi, const std::string& source) {
  if (!lo.allFinite() || !hi.allFinite() || !((hi - lo).array() > 0.0).all())
    throw InputError(SourceLoc{source},
                     fmt::format("box needs min < max on every axis, got min {} max {}", fmt_point(lo), fmt_point(hi)));
  Mesh m;
  m.source = source;
  for (int i = 0; i < 8; ++i)
    m.vertices_mm.emplace_back(i & 1 ? hi.x() : lo.x(), i & 2 ? hi.y() : lo.y(), i & 4 ? hi.z() : lo.z());
  // Quads counter-clockwise seen from outside, two triangles each.
  const int q[6][4] = {{0, 2, 3, 1}, {4, 5, 7, 6}, {0, 1, 5, 4}, {2, 6, 7, 3}, {0, 4, 6, 2}, {1, 3, 7, 5}};
  for (const auto& f : q) {
    m.triangles.emplace_back(f[0], f[1], f[2]);
    m.triangles.emplace_back(f[0], f[2], f[3]);
  }
  return m;
}

Mesh cylinder_mesh(const Eigen::Vector3d& from, const Eigen::Vector3d& to, double diameter_mm, int sides,
                   const std::string& source) {
  const Eigen::Vector3d axis = to - from;
  const double length = axis.norm();
  if (!from.allFinite() || !to.allFinite() || !(length > 0.0) || !(diameter_mm > 0.0) || !std::isfinite(diameter_mm) ||
      sides < 3)
    throw InputError(SourceLoc{source},
                     fmt::format("cylinder needs a positive diameter ({}) and length ({}) and >= 3 sides ({})",
                                 diameter_mm, length, sides));
  const Eigen::Vector3d w = axis / length;
  const Eigen::Vector3d u = w.unitOrthogonal(), v = w.cross(u);
  const double pi = 3.14159265358979323846;
  const double rc = 0.5 * diameter_mm / std::cos(pi / sides);  // circumscribed
  Mesh m;
  m.source = source;
  for (int k = 0; k < sides; ++k) {
    const double a = 2.0 * pi * k / sides;
    const Eigen::Vector3d d = rc * (std::cos(a) * u + std::sin(a) * v);
    m.vertices_mm.push_back(from + d);
    m.vertices_mm.push_back(to + d);
  }
  const int c0 = 2 * sides, c1 = c0 + 1;
  m.vertices_mm.push_back(from);
  m.vertices_mm.push_back(to);
  for (int k = 0; k < sides; ++k) {
    const int a0 = 2 * k, a1 = a0 + 1, b0 = 2 * ((k + 1) % sides), b1 = b0 + 1;
    // (u, v, w) is right-handed, so the side quad a0 b0 b1 a1 is counter-clockwise seen from outside.
    m.triangles.emplace_back(a0, b0, b1);
    m.triangles.emplace_back(a0, b1, a1);
    m.triangles.emplace_back(c0, b0, a0);  // bottom cap faces -w
    m.triangles.emplace_back(c1, a1, b1);  // top cap faces +w
  }
  return m;
}

void Mesh::transform(const Eigen::Isometry3d& T) {
  for (auto& v : vertices_mm) v = T * v;
}

void Mesh::append(const Mesh& other) {
  const int base = static_cast<int>(vertices_mm.size());
  vertices_mm.insert(vertices_mm.end(), other.vertices_mm.begin(), other.vertices_mm.end());
  triangles.reserve(triangles.size() + other.triangles.size());
  for (const auto& t : other.triangles) triangles.emplace_back(t.array() + base);
}

namespace {

/// Element counts an OFF header declares (vertices, faces, edges), after the keyword if there is one (assimp also
/// reads a .off file without it); comments skipped.
std::vector<double> off_counts(const std::string& head, bool has_keyword) {
  std::vector<double> counts;
  size_t i = has_keyword ? head.find_first_of(" \t\r\n") : 0;  // past the keyword
  while (i != std::string::npos && i < head.size() && counts.size() < 3) {
    if (head[i] == '#') {
      i = head.find('\n', i);
      continue;
    }
    if (std::isspace(static_cast<unsigned char>(head[i]))) {
      ++i;
      continue;
    }
    const size_t j = std::min(head.find_first_of(" \t\r\n#", i), head.size());
    char* stop = nullptr;
    const std::string token = head.substr(i, j - i);
    const double v = std::strtod(token.c_str(), &stop);
    if (stop == token.c_str()) break;  // not a count: assimp will say what is wrong
    counts.push_back(v);
    i = j;
  }
  return counts;
}

/// Element counts a PLY header declares ("element <name> <count>").
std::vector<double> ply_counts(const std::string& header) {
  std::vector<double> counts;
  std::istringstream in(header);
  for (std::string line; std::getline(in, line);) {
    std::istringstream words(line);
    std::string kw, name, count;
    if (words >> kw >> name >> count && kw == "element") counts.push_back(std::strtod(count.c_str(), nullptr));
  }
  return counts;
}

/// Every declared element takes at least one byte in any encoding, so counts beyond the file's size are a
/// corrupt header; assimp would try to allocate them first (fuzzing found 0x620cd9558-byte requests).
void check_declared_counts(const std::string& path, const std::vector<double>& counts, double file_bytes) {
  double total = 0.0;
  for (const double c : counts) total += std::max(0.0, c);
  if (total > file_bytes)
    throw InputError(SourceLoc{path, 1, 0}, fmt::format("mesh header declares {:.0f} elements, more than the file's "
                                                        "{:.0f} bytes can hold: the header is corrupt",
                                                        total, file_bytes));
}

Mesh load_mesh_here(const std::string& path, double scale_to_mm, bool require_closed) {
  const SourceLoc where{path};
  if (!(scale_to_mm > 0.0) || !std::isfinite(scale_to_mm))
    throw InputError(where, fmt::format("scale to mm must be a positive number, got {}", scale_to_mm));
  {
    std::ifstream probe(path, std::ios::binary);
    if (!probe) throw InputError(where, "cannot open mesh file");
    // assimp 5.2's PLY reader loops forever on a header without end_header (found by fuzz/mesh_fuzz): a
    // PLY file must close its header within the first 64 KiB before assimp sees it.
    std::string head(65536, '\0');
    probe.read(head.data(), static_cast<std::streamsize>(head.size()));
    head.resize(static_cast<size_t>(probe.gcount()));
    // OFF is a text format; assimp 5.2 aborts in post-processing on some malformed binary bytes in it.
    const bool is_off = head.rfind("OFF", 0) == 0 || head.rfind("COFF", 0) == 0 || head.rfind("NOFF", 0) == 0;
    probe.clear();
    probe.seekg(0, std::ios::end);
    const double file_bytes = static_cast<double>(probe.tellg());
    if (is_off) {
      std::ifstream all(path, std::ios::binary);
      int line = 1;
      for (char c; all.get(c);) {
        if (c == '\n')
          ++line;
        else if (c != '\r' && c != '\t' && (static_cast<unsigned char>(c) < 32 || static_cast<unsigned char>(c) > 126))
          throw InputError(SourceLoc{path, line, 0}, "OFF mesh contains a byte that is not text");
      }
    }
    std::string ext = std::filesystem::path(path).extension().string();
    std::transform(ext.begin(), ext.end(), ext.begin(), [](unsigned char c) { return std::tolower(c); });
    if (is_off || ext == ".off") check_declared_counts(path, off_counts(head, is_off), file_bytes);
    if (head.rfind("ply", 0) == 0) {
      const size_t end = head.find("end_header");
      if (end == std::string::npos)
        throw InputError(where, "PLY header has no end_header line within its first 64 KiB");
      for (size_t i = 0; i < end; ++i)
        if (head[i] != '\n' && head[i] != '\r' && (head[i] < 32 || head[i] > 126))
          throw InputError(
              SourceLoc{path, 1 + static_cast<int>(std::count(head.begin(), head.begin() + static_cast<long>(i), '\n')),
                        0},
              "PLY header contains a byte that is not printable text");
      check_declared_counts(path, ply_counts(head.substr(0, end)), file_bytes);
    }
  }
  Assimp::Importer importer;
  importer.SetPropertyInteger(AI_CONFIG_PP_RVC_FLAGS, aiComponent_NORMALS | aiComponent_TANGENTS_AND_BITANGENTS |
                                                          aiComponent_COLORS | aiComponent_TEXCOORDS |
                                                          aiComponent_BONEWEIGHTS);
  importer.SetPropertyInteger(AI_CONFIG_PP_SBP_REMOVE, aiPrimitiveType_POINT | aiPrimitiveType_LINE);
  // RemoveComponent first: STL stores a normal per face corner, which would stop JoinIdenticalVertices
  // from welding the corners of neighbouring faces.
  const aiScene* scene = importer.ReadFile(path, aiProcess_RemoveComponent | aiProcess_JoinIdenticalVertices |
                                                     aiProcess_Triangulate | aiProcess_SortByPType);
  if (!scene || !scene->mRootNode)
    throw InputError(where, fmt::format("cannot read mesh: {}", importer.GetErrorString()));
  if (scene->mFlags & AI_SCENE_FLAGS_INCOMPLETE)
    throw InputError(where, fmt::format("mesh file is incomplete: {}", importer.GetErrorString()));

  Mesh mesh;
  mesh.source = path;
  aiMatrix4x4 identity;
  collect(scene, scene->mRootNode, identity, scale_to_mm, mesh);
  if (mesh.triangles.empty()) throw InputError(where, "mesh file contains no triangles");
  for (const auto& v : mesh.vertices_mm)
    if (!v.allFinite()) throw InputError(where, "mesh file contains a non-finite vertex coordinate");

  // Weld across sub-meshes (assimp only joins within one mesh), tolerance relative to the part size.
  const double diag = mesh.bounding_box().diagonal().norm();
  mesh.collapsed_at_load = weld(mesh, std::max(diag * 1e-7, 1e-12));
  if (mesh.triangles.empty()) throw InputError(where, "mesh file contains only degenerate triangles");

  if (require_closed) {
    std::string why;
    if (!mesh.is_closed(&why)) throw InputError(where, why);
  }
  return mesh;
}

// The child's answer on the pipe: 'M' + mesh, or 'E' + line, column, message (an InputError).
void put(std::string& out, const void* p, size_t n) { out.append(static_cast<const char*>(p), n); }
template <typename T>
bool get(const std::string& in, size_t& at, T& v) {
  if (at + sizeof(T) > in.size()) return false;
  std::memcpy(&v, in.data() + at, sizeof(T));
  at += sizeof(T);
  return true;
}

}  // namespace

Mesh load_mesh(const std::string& path, double scale_to_mm, bool require_closed) {
  // assimp runs in a child process: a third-party reader that hangs or aborts on a hostile file (fuzzing found
  // both) must end in a file error, not a hung or crashed cscam. Bounded in time by CSCAM_MESH_TIMEOUT_S (60).
  int fd[2];
  if (::pipe(fd) != 0) return load_mesh_here(path, scale_to_mm, require_closed);
  const pid_t pid = ::fork();
  if (pid < 0) {
    ::close(fd[0]);
    ::close(fd[1]);
    return load_mesh_here(path, scale_to_mm, require_closed);
  }
  if (pid == 0) {
    ::close(fd[0]);
    // The parent's crash handlers (a host application's, a fuzzer's) must not run here: a reader that aborts is
    // the parent's to report, as a file error, from the child's exit signal.
    for (const int sig : {SIGABRT, SIGSEGV, SIGBUS, SIGFPE, SIGILL}) ::signal(sig, SIG_DFL);
    std::string out;
    try {
      const Mesh m = load_mesh_here(path, scale_to_mm, require_closed);
      out.push_back('M');
      const uint64_t nv = m.vertices_mm.size(), nt = m.triangles.size();
      put(out, &nv, sizeof nv);
      for (const auto& v : m.vertices_mm) put(out, v.data(), 3 * sizeof(double));
      put(out, &nt, sizeof nt);
      for (const auto& t : m.triangles) put(out, t.data(), 3 * sizeof(int));
      const uint64_t collapsed = m.collapsed_at_load;
      put(out, &collapsed, sizeof collapsed);
    } catch (const InputError& e) {
      out.assign(1, 'E');
      const int32_t line = e.where().line, col = e.where().column;
      put(out, &line, sizeof line);
      put(out, &col, sizeof col);
      out += e.message();
    } catch (const std::exception& e) {
      out.assign(1, 'E');
      const int32_t zero = 0;
      put(out, &zero, sizeof zero);
      put(out, &zero, sizeof zero);
      out += std::string("cannot read mesh: ") + e.what();
    }
    for (size_t done = 0; done < out.size();) {
      const ssize_t w = ::write(fd[1], out.data() + done, out.size() - done);
      if (w <= 0) break;
      done += static_cast<size_t>(w);
    }
    ::_exit(0);
  }
  ::close(fd[1]);
  double limit_s = 60.0;
  if (const char* e = std::getenv("CSCAM_MESH_TIMEOUT_S")) limit_s = std::max(0.1, std::atof(e));
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::duration<double>(limit_s);
  std::string in;
  bool timed_out = false;
  for (;;) {
    const auto left =
        std::chrono::duration_cast<std::chrono::milliseconds>(deadline - std::chrono::steady_clock::now());
    if (left.count() <= 0) {
      timed_out = true;
      break;
    }
    pollfd pfd{fd[0], POLLIN, 0};
    const int r = ::poll(&pfd, 1, static_cast<int>(std::min<long long>(left.count(), 1000)));
    if (r < 0 && errno == EINTR) continue;
    if (r <= 0) continue;
    char buf[65536];
    const ssize_t n = ::read(fd[0], buf, sizeof buf);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) break;
    in.append(buf, static_cast<size_t>(n));
  }
  ::close(fd[0]);
  int status = 0;
  // The child may linger after closing its end of the pipe (a sanitizer or a crash reporter at work in it): the
  // same deadline bounds its exit, so the loader never waits unbounded.
  while (!timed_out) {
    const pid_t done = ::waitpid(pid, &status, WNOHANG);
    if (done == pid || (done < 0 && errno != EINTR)) break;
    if (std::chrono::steady_clock::now() >= deadline) {
      timed_out = true;
      break;
    }
    ::usleep(2000);
  }
  if (timed_out) {
    ::kill(pid, SIGKILL);
    while (::waitpid(pid, &status, 0) < 0 && errno == EINTR) {
    }
  }
  const SourceLoc where{path};
  if (timed_out)
    throw InputError(where, fmt::format("the mesh reader (assimp) did not finish within {:.0f} s: the file is "
                                        "malformed or too large (CSCAM_MESH_TIMEOUT_S sets the limit)",
                                        limit_s));
  if (WIFSIGNALED(status))
    throw InputError(where, fmt::format("the mesh reader (assimp) crashed on this file (signal {}): it is malformed",
                                        WTERMSIG(status)));
  size_t at = 1;
  if (!in.empty() && in[0] == 'E') {
    int32_t line = 0, col = 0;
    get(in, at, line);
    get(in, at, col);
    throw InputError(SourceLoc{path, line, col}, in.substr(std::min(at, in.size())));
  }
  Mesh mesh;
  mesh.source = path;
  uint64_t nv = 0, nt = 0;
  bool ok = !in.empty() && in[0] == 'M' && get(in, at, nv) && nv < (1ull << 32);
  for (uint64_t i = 0; ok && i < nv; ++i) {
    Eigen::Vector3d v;
    ok = get(in, at, v[0]) && get(in, at, v[1]) && get(in, at, v[2]);
    mesh.vertices_mm.push_back(v);
  }
  ok = ok && get(in, at, nt) && nt < (1ull << 32);
  for (uint64_t i = 0; ok && i < nt; ++i) {
    Eigen::Vector3i t;
    ok = get(in, at, t[0]) && get(in, at, t[1]) && get(in, at, t[2]);
    mesh.triangles.push_back(t);
  }
  uint64_t collapsed = 0;
  ok = ok && get(in, at, collapsed);
  mesh.collapsed_at_load = static_cast<std::size_t>(collapsed);
  if (!ok || at != in.size())
    throw InputError(where, "the mesh reader (assimp) ended without an answer: the file is malformed");
  return mesh;
}

void save_stl(const Mesh& mesh, const std::string& path) {
  static_assert(std::endian::native == std::endian::little, "binary STL writer assumes a little-endian host");
  const auto n = static_cast<std::uint32_t>(mesh.triangles.size());
  CSCAM_CHECK(mesh.triangles.size() == n, "too many triangles for STL");
  write_file_atomically(path, [&](std::ostream& out) {
    std::array<char, 80> header{};
    const std::string title = "cscam binary STL " + mesh.source;  // must not start with "solid"
    std::memcpy(header.data(), title.data(), std::min(title.size(), header.size()));
    out.write(header.data(), static_cast<std::streamsize>(header.size()));
    out.write(reinterpret_cast<const char*>(&n), sizeof n);
    std::array<char, 50> rec{};
    for (const auto& t : mesh.triangles) {
      const Eigen::Vector3d& a = mesh.vertices_mm.at(static_cast<std::size_t>(t[0]));
      const Eigen::Vector3d& b = mesh.vertices_mm.at(static_cast<std::size_t>(t[1]));
      const Eigen::Vector3d& c = mesh.vertices_mm.at(static_cast<std::size_t>(t[2]));
      Eigen::Vector3d nrm = (b - a).cross(c - a);
      const double len = nrm.norm();
      nrm = len > 0.0 ? Eigen::Vector3d(nrm / len) : Eigen::Vector3d::Zero();
      std::array<float, 12> f{};
      for (int k = 0; k < 3; ++k) {
        f[static_cast<std::size_t>(k)] = static_cast<float>(nrm[k]);
        f[static_cast<std::size_t>(3 + k)] = static_cast<float>(a[k]);
        f[static_cast<std::size_t>(6 + k)] = static_cast<float>(b[k]);
        f[static_cast<std::size_t>(9 + k)] = static_cast<float>(c[k]);
      }
      std::memcpy(rec.data(), f.data(), sizeof f);  // 48 bytes, then a zero attribute word
      out.write(rec.data(), static_cast<std::streamsize>(rec.size()));
    }
  });
}

}  // namespace cscam::geom
