// Exclusive prefix sum of u32s in place, in 256-element blocks: each block
// scans itself and writes its total; the host scans the totals the same way
// and adds each block's offset.

@group(0) @binding(0) var<uniform> pass_: Pass;
@group(0) @binding(1) var<storage, read_write> data: array<u32>;
@group(0) @binding(2) var<storage, read_write> block_sums: array<u32>;

var<workgroup> partial: array<u32, 256>;

@compute @workgroup_size(256)
fn scan_blocks(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let block = flat_block(wid, nwg);
    if block >= pass_.blocks {
        return;
    }
    let i = block * 256u + lid;
    var v = 0u;
    if i < pass_.count {
        v = data[i];
    }
    partial[lid] = v;
    workgroupBarrier();
    // Hillis-Steele inclusive scan.
    for (var offset = 1u; offset < 256u; offset *= 2u) {
        var left = 0u;
        if lid >= offset {
            left = partial[lid - offset];
        }
        workgroupBarrier();
        partial[lid] += left;
        workgroupBarrier();
    }
    if i < pass_.count {
        data[i] = partial[lid] - v;
    }
    if lid == 255u {
        block_sums[block] = partial[255];
    }
}

@compute @workgroup_size(256)
fn add_block_offsets(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let block = flat_block(wid, nwg);
    let i = block * 256u + lid;
    if block < pass_.blocks && i < pass_.count {
        data[i] += block_sums[block];
    }
}
