// Each tile's [start, end) in the tile-sorted intersection list (empty tiles
// keep the zero-initialised 0..0).

@group(0) @binding(0) var<uniform> pass_: Pass;
@group(0) @binding(1) var<storage, read> tile_keys: array<u32>;
@group(0) @binding(2) var<storage, read_write> ranges: array<u32>;

@compute @workgroup_size(256)
fn main(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let i = flat_block(wid, nwg) * 256u + lid;
    if i >= pass_.count {
        return;
    }
    let tile = tile_keys[i];
    if i == 0u || tile_keys[i - 1u] != tile {
        ranges[2u * tile] = i;
    }
    if i + 1u == pass_.count || tile_keys[i + 1u] != tile {
        ranges[2u * tile + 1u] = i + 1u;
    }
}
