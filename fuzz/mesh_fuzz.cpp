// libFuzzer target: mesh loading through assimp (STL ASCII/binary, OBJ, PLY, OFF by content), bounded in
// size. The first byte picks the file extension so that every importer is reached.
#include <unistd.h>

#include <cstddef>
#include <cstdint>
#include <fstream>
#include <string>

#include "cscam/core/error.hpp"
#include "cscam/geom/mesh.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  if (size < 1 || size > (1u << 16)) return -1;
  static const char* kExt[] = {".stl", ".obj", ".ply", ".off"};
  const std::string path = "/tmp/cscam_mesh_fuzz_" + std::to_string(::getpid()) + kExt[data[0] % 4];
  {
    std::ofstream out(path, std::ios::binary);
    out.write(reinterpret_cast<const char*>(data + 1), static_cast<std::streamsize>(size - 1));
  }
  try {
    (void)cscam::geom::load_mesh(path, 1.0, false);
  } catch (const cscam::InputError&) {
  }
  ::unlink(path.c_str());
  return 0;
}
