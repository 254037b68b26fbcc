#include "cscam/core/atomic_file.hpp"

#include <fmt/format.h>
#include <unistd.h>

#include <filesystem>
#include <vector>

#include "cscam/core/error.hpp"

namespace cscam {

void write_file_atomically(const std::string& path, const std::function<void(std::ostream&)>& write) {
  namespace fs = std::filesystem;
  const fs::path target(path);
  const fs::path dir = target.has_parent_path() ? target.parent_path() : fs::path(".");
  if (!fs::is_directory(dir)) throw InputError(SourceLoc{path}, "output directory does not exist");
  // The temporary lives in the same directory so that rename() is atomic (same file system).
  const fs::path tmp = dir / fmt::format(".{}.tmp.{}", target.filename().string(), ::getpid());
  try {
    std::vector<char> buffer(1 << 20);
    std::ofstream out;
    out.rdbuf()->pubsetbuf(buffer.data(), static_cast<std::streamsize>(buffer.size()));
    out.open(tmp, std::ios::binary | std::ios::trunc);
    if (!out) throw InputError(SourceLoc{path}, "cannot open a temporary file for writing");
    write(out);
    out.flush();
    if (!out) throw InputError(SourceLoc{path}, "write failed (disk full?)");
    out.close();
    fs::rename(tmp, target);
  } catch (...) {
    std::error_code ec;
    fs::remove(tmp, ec);
    throw;
  }
}

}  // namespace cscam
