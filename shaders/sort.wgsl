// One pass of a stable least-significant-digit radix sort of (key, value)
// pairs on 8 bits of the key at `shift`: per 256-element block a digit
// histogram, then (after an exclusive scan of the digit-major counts, scan.wgsl)
// a scatter in which each element goes after the earlier elements of its block
// with the same digit, which keeps the sort stable.

@group(0) @binding(0) var<uniform> pass_: Pass;
@group(0) @binding(1) var<storage, read> keys_in: array<u32>;
@group(0) @binding(2) var<storage, read> values_in: array<u32>;
@group(0) @binding(3) var<storage, read_write> block_counts: array<u32>;
@group(0) @binding(4) var<storage, read_write> keys_out: array<u32>;
@group(0) @binding(5) var<storage, read_write> values_out: array<u32>;

var<workgroup> histogram_: array<atomic<u32>, 256>;
var<workgroup> digits: array<u32, 256>;

fn digit_of(key: u32) -> u32 {
    return (key >> pass_.shift) & 255u;
}

@compute @workgroup_size(256)
fn count_digits(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let block = flat_block(wid, nwg);
    if block >= pass_.blocks {
        return;
    }
    atomicStore(&histogram_[lid], 0u);
    workgroupBarrier();
    let i = block * 256u + lid;
    if i < pass_.count {
        atomicAdd(&histogram_[digit_of(keys_in[i])], 1u);
    }
    workgroupBarrier();
    // Digit-major: the scan then gives every (digit, block) its first slot.
    block_counts[lid * pass_.blocks + block] = atomicLoad(&histogram_[lid]);
}

@compute @workgroup_size(256)
fn scatter(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let block = flat_block(wid, nwg);
    if block >= pass_.blocks {
        return;
    }
    let i = block * 256u + lid;
    // 256 is no digit: padding lanes match nothing.
    var d = 256u;
    if i < pass_.count {
        d = digit_of(keys_in[i]);
    }
    digits[lid] = d;
    workgroupBarrier();
    if i < pass_.count {
        var rank = 0u;
        for (var j = 0u; j < lid; j++) {
            rank += select(0u, 1u, digits[j] == d);
        }
        let dest = block_counts[d * pass_.blocks + block] + rank;
        keys_out[dest] = keys_in[i];
        values_out[dest] = values_in[i];
    }
}
