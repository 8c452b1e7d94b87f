// Nearest hits in an Embree 4 scene, the rays spread over OpenMP threads (geometry/embree_scene.py builds the
// scene on the mesh's own arrays). The binding embreex answered the same queries, but it fills Embree's buffers
// element by element in Python-level code (6.2 s for the 10M lattice) and copies them (193 MiB there).
//
// Embree's ray layout, declared here from its API documentation (rtcore_ray.h, Embree 4): RTCRay is 12 four-byte
// fields; RTCHit follows it, 16-byte aligned, with primID and geomID at bytes 20 and 24. The hit is given room
// for the instance IDs a build may add after them; only the fields below are read or written.
#include "common.h"

namespace {

constexpr uint32_t kInvalidId = 0xFFFFFFFFu;

struct alignas(16) RayHit {
    float org_x, org_y, org_z, tnear;
    float dir_x, dir_y, dir_z, time;
    float tfar;
    uint32_t mask, id, flags;
    float ng_x, ng_y, ng_z, u, v;
    uint32_t prim_id, geom_id;
    uint32_t inst_ids[16];  // instID[] (and instPrimID[]) of builds with instancing levels: never read
};
static_assert(offsetof(RayHit, prim_id) == 48 + 20, "RTCHit.primID follows RTCRay's 48 bytes at offset 20");

using IntersectFn = void (*)(void* scene, RayHit* ray_hit, void* args);

}  // namespace

extern "C" void nbvh_embree_first_hits(void* intersect, void* scene, const float* rays_o, const float* rays_d,
                                       const float* t_max, int64_t n, float* out_t, int32_t* out_prim,
                                       int threads) {
    auto fn = reinterpret_cast<IntersectFn>(intersect);
#pragma omp parallel for schedule(static, 1024) num_threads(threads)
    for (int64_t i = 0; i < n; ++i) {
        RayHit r;
        std::memset(&r, 0, sizeof(r));
        r.org_x = rays_o[3 * i], r.org_y = rays_o[3 * i + 1], r.org_z = rays_o[3 * i + 2];
        r.dir_x = rays_d[3 * i], r.dir_y = rays_d[3 * i + 1], r.dir_z = rays_d[3 * i + 2];
        r.tnear = 0.0f;
        r.tfar = t_max[i];
        r.mask = kInvalidId;
        r.prim_id = r.geom_id = kInvalidId;
        std::fill(std::begin(r.inst_ids), std::end(r.inst_ids), kInvalidId);
        fn(scene, &r, nullptr);
        const bool hit = r.geom_id != kInvalidId;
        out_t[i] = r.tfar;
        out_prim[i] = hit ? static_cast<int32_t>(r.prim_id) : -1;
    }
}
