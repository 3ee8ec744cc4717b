// From the depth-sorted Gaussians to per-tile lists: each visible Gaussian's
// tile count in depth order, its (tile, depth rank) intersections, and, once
// those are sorted by tile (stably, so each tile's list stays front to back),
// each tile's range of the sorted list.

@group(0) @binding(0) var<uniform> frame: Frame;
@group(0) @binding(1) var<storage, read> depth_order: array<u32>;
@group(0) @binding(2) var<storage, read> tile_counts: array<u32>;
@group(0) @binding(3) var<storage, read_write> rank_offsets: array<u32>;
@group(0) @binding(4) var<storage, read> tile_spans: array<vec4<u32>>;
@group(0) @binding(5) var<storage, read_write> tile_keys: array<u32>;
@group(0) @binding(6) var<storage, read_write> tile_values: array<u32>;

// rank_offsets[r] = tile count of the r-th nearest Gaussian (scanned next).
@compute @workgroup_size(256)
fn counts_by_rank(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let r = flat_block(wid, nwg) * 256u + lid;
    if r < frame.sizes.x {
        rank_offsets[r] = tile_counts[depth_order[r]];
    }
}

// One (tile, rank) pair per tile a Gaussian touches, at its scanned offset.
@compute @workgroup_size(256)
fn emit_intersections(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let r = flat_block(wid, nwg) * 256u + lid;
    if r >= frame.sizes.x {
        return;
    }
    let span = tile_spans[depth_order[r]];
    var slot = rank_offsets[r];
    for (var ty = span.y; ty <= span.w; ty++) {
        for (var tx = span.x; tx <= span.z; tx++) {
            tile_keys[slot] = ty * frame.image.z + tx;
            tile_values[slot] = r;
            slot++;
        }
    }
}
