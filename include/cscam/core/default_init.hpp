#pragma once
/// @file
/// An allocator whose value-less construct() default-initialises: resize() of a vector of trivial elements then
/// leaves them unwritten. For large arrays that a parallel loop fills next: the pages are first touched (and
/// zeroed by the kernel) by the threads that fill them, not by one thread writing zeros before.
#include <memory>
#include <new>
#include <utility>

namespace cscam {

template <typename T>
struct DefaultInitAllocator : std::allocator<T> {
  using std::allocator<T>::allocator;
  template <typename U>
  struct rebind {
    using other = DefaultInitAllocator<U>;
  };
  template <typename U>
  void construct(U* p) noexcept(std::is_nothrow_default_constructible_v<U>) {
    ::new (static_cast<void*>(p)) U;
  }
  template <typename U, typename... Args>
  void construct(U* p, Args&&... args) {
    ::new (static_cast<void*>(p)) U(std::forward<Args>(args)...);
  }
};

}  // namespace cscam
