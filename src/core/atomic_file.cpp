#include "cscam/core/atomic_file.hpp"

#include <fmt/format.h>
#include <unistd.h>

#include <vector>

#include "cscam/core/error.hpp"

namespace cscam {

void write_file_atomically(const std::string& path, const std::function<void(std::ostream&)>& write) {
  PendingFile file(path);
  file.write(write);
  file.commit();
}

PendingFile::~PendingFile() { remove_temporary(); }

void PendingFile::remove_temporary() noexcept {
  if (tmp_.empty()) return;
  std::error_code ec;
  std::filesystem::remove(tmp_, ec);
  tmp_.clear();
}

void PendingFile::write(const std::function<void(std::ostream&)>& write) {
  namespace fs = std::filesystem;
  remove_temporary();
  const fs::path target(path_);
  const fs::path dir = target.has_parent_path() ? target.parent_path() : fs::path(".");
  if (!fs::is_directory(dir)) throw InputError(SourceLoc{path_}, "output directory does not exist");
  // The temporary lives in the same directory so that rename() is atomic (same file system).
  tmp_ = dir / fmt::format(".{}.tmp.{}", target.filename().string(), ::getpid());
  try {
    std::vector<char> buffer(1 << 20);
    std::ofstream out;
    out.rdbuf()->pubsetbuf(buffer.data(), static_cast<std::streamsize>(buffer.size()));
    out.open(tmp_, std::ios::binary | std::ios::trunc);
    if (!out) throw InputError(SourceLoc{path_}, "cannot open a temporary file for writing");
    write(out);
    out.flush();
    if (!out) throw InputError(SourceLoc{path_}, "write failed (disk full?)");
    out.close();
  } catch (...) {
    remove_temporary();
    throw;
  }
}

void PendingFile::commit() {
  try {
    std::filesystem::rename(tmp_, std::filesystem::path(path_));
    tmp_.clear();
  } catch (...) {
    remove_temporary();
    throw;
  }
}

}  // namespace cscam
