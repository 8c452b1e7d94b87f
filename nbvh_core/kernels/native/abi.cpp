// The ABI the library was built against: the hash of nbvh_kernels.h, passed by the build (kernels/library.py).
#include "nbvh_kernels.h"

extern "C" uint64_t nbvh_abi_hash() { return NBVH_ABI_HASH; }
