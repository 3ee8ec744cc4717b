//! The GPU backend: the CPU backend's rasterizer, forward and backward, as WGSL
//! compute kernels (shaders/) run through wgpu on Vulkan, Metal or DX12.
//!
//! One render is a fixed chain of kernels, in the shape of brush and gsplat:
//! project every Gaussian (`project.wgsl`), radix-sort the visible ones by depth
//! (`sort.wgsl`, `scan.wgsl`), emit one (tile, depth rank) pair per tile each
//! touches and sort those stably by tile (`bin.wgsl`), find each tile's range
//! (`tile_ranges.wgsl`), then composite one workgroup per 16x16 tile
//! (`rasterize.wgsl`). The backward pass walks each tile's list back to front
//! (`rasterize_backward.wgsl`) and then backs the projection up to the raw
//! parameters (`project_backward.wgsl`). The numeric rules (culling, the 0.3 px^2
//! dilation, alpha thresholds, the exp polynomial) are the CPU backend's, so the
//! two agree to float rounding; the per-Gaussian gradient sums over tiles are
//! float atomics, so their last bits depend on the GPU's scheduling.

use std::sync::Arc;

use bytemuck::{Pod, Zeroable};
use glam::Vec3;
use wgpu::util::DeviceExt;

use super::project::ProjectionCamera;
use super::raster::{RasterOutput, TILE};
use super::{Gradients, Prepared, RenderOptions};
use crate::camera::Camera;
use crate::splat::{GaussianSet, ParamGroup};

/// Threads per workgroup of the 1D kernels (and elements per sort or scan block).
const GROUP: u32 = 256;
/// The constants, uniforms and helpers every kernel's module starts with.
pub(crate) const COMMON_WGSL: &str = include_str!("../../shaders/common.wgsl");

/// Most workgroups one dispatch dimension may hold (WebGPU's limit).
const MAX_GROUPS_PER_DIM: u32 = 65_535;
/// Floats per projected Gaussian and per projected-gradient record (common.wgsl).
const SPLAT_STRIDE: u64 = 10;
const GRAD_STRIDE: usize = 10;

/// Why no GPU backend could be made.
#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    #[error("no {wanted} found (wgpu found: {found}); install a Vulkan driver (e.g. mesa-vulkan-drivers) or use --backend cpu")]
    NoAdapter { wanted: &'static str, found: String },
    #[error("the GPU adapter {adapter} refused a device: {message}")]
    Device { adapter: String, message: String },
}

/// A scene too large for the device: one of its buffers exceeds the largest
/// storage buffer the device allows.
#[derive(Debug, thiserror::Error)]
#[error("{what} need {bytes} bytes on the GPU, more than its largest buffer ({limit} bytes)")]
pub struct GpuLimit {
    pub what: &'static str,
    pub bytes: u64,
    pub limit: u64,
}

/// The first of `buffers` (bytes, with what they hold) larger than `limit`.
fn check_buffer_sizes(buffers: &[(&'static str, u64)], limit: u64) -> Result<(), GpuLimit> {
    match buffers.iter().find(|(_, bytes)| *bytes > limit) {
        Some(&(what, bytes)) => Err(GpuLimit { what, bytes, limit }),
        None => Ok(()),
    }
}

/// Which adapters a [`GpuContext`] may use.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AdapterKind {
    /// Any adapter, software rasterizers (lavapipe) included.
    Any,
    /// A hardware GPU only (discrete, integrated or virtual).
    Hardware,
}

/// A GPU device with the rasterizer's kernels compiled for it.
pub struct GpuContext {
    device: wgpu::Device,
    queue: wgpu::Queue,
    info: wgpu::AdapterInfo,
    kernels: Kernels,
}

struct Kernels {
    project: wgpu::ComputePipeline,
    count_digits: wgpu::ComputePipeline,
    scatter: wgpu::ComputePipeline,
    scan_blocks: wgpu::ComputePipeline,
    add_block_offsets: wgpu::ComputePipeline,
    counts_by_rank: wgpu::ComputePipeline,
    emit_intersections: wgpu::ComputePipeline,
    tile_ranges: wgpu::ComputePipeline,
    rasterize: wgpu::ComputePipeline,
    rasterize_backward: wgpu::ComputePipeline,
    project_backward: wgpu::ComputePipeline,
}

/// The per-render uniforms (`Frame` in common.wgsl).
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct FrameUniform {
    rotation: [[f32; 4]; 3],
    translation: [f32; 4],
    position: [f32; 4],
    intrinsics: [f32; 4],
    limits: [f32; 4],
    background: [f32; 4],
    image: [u32; 4],
    sizes: [u32; 4],
    offsets: [u32; 4],
    offsets2: [u32; 4],
}

/// The sizes of one sort, scan or range pass (`Pass` in common.wgsl).
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct PassUniform {
    count: u32,
    shift: u32,
    blocks: u32,
    unused: u32,
}

/// A view rendered on the GPU: its images (read back) and the device buffers
/// its backward pass reuses.
pub struct GpuRender {
    pub width: u32,
    pub height: u32,
    /// Row-major RGB (background included), alpha, accumulated depth, final
    /// transmittance and last composited list position, as the CPU backend's.
    pub image: RasterOutput,
    /// Rows of each rendered set.
    set_sizes: Vec<usize>,
    background: BackgroundPixels,
    frame: wgpu::Buffer,
    params: wgpu::Buffer,
    splats: wgpu::Buffer,
    tile_counts: wgpu::Buffer,
    depth_order: wgpu::Buffer,
    tile_values: wgpu::Buffer,
    ranges: wgpu::Buffer,
    state: wgpu::Buffer,
}

/// The background a render composited over, kept for the backward pass.
#[derive(Clone)]
enum BackgroundPixels {
    Uniform(Vec3),
    Image(Arc<[f32]>),
}

impl BackgroundPixels {
    fn at(&self, pixel: usize) -> Vec3 {
        match self {
            BackgroundPixels::Uniform(c) => *c,
            BackgroundPixels::Image(img) => Vec3::from_slice(&img[3 * pixel..3 * pixel + 3]),
        }
    }
}

impl GpuContext {
    /// Open the best adapter of `kind` (discrete before integrated before
    /// virtual before software) and compile the kernels for it.
    pub fn new(kind: AdapterKind) -> Result<Self, GpuError> {
        let instance = wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        let adapters = pollster::block_on(instance.enumerate_adapters(wgpu::Backends::all()));
        let found: Vec<String> =
            adapters.iter().map(|a| format!("{} ({:?})", a.get_info().name, a.get_info().device_type)).collect();
        let rank = |t: wgpu::DeviceType| match t {
            wgpu::DeviceType::DiscreteGpu => Some(0),
            wgpu::DeviceType::IntegratedGpu => Some(1),
            wgpu::DeviceType::VirtualGpu => Some(2),
            wgpu::DeviceType::Cpu | wgpu::DeviceType::Other => (kind == AdapterKind::Any).then_some(3),
        };
        let adapter = adapters
            .into_iter()
            .filter_map(|a| rank(a.get_info().device_type).map(|r| (r, a)))
            .min_by_key(|(r, _)| *r)
            .map(|(_, a)| a)
            .ok_or_else(|| GpuError::NoAdapter {
                wanted: match kind {
                    AdapterKind::Any => "GPU adapter",
                    AdapterKind::Hardware => "hardware GPU adapter",
                },
                found: if found.is_empty() { "none".into() } else { found.join(", ") },
            })?;
        let info = adapter.get_info();
        // The adapter's own limits: big scenes need storage buffers beyond WebGPU's defaults.
        let descriptor =
            wgpu::DeviceDescriptor { label: Some("aim"), required_limits: adapter.limits(), ..Default::default() };
        let (device, queue) = pollster::block_on(adapter.request_device(&descriptor))
            .map_err(|e| GpuError::Device { adapter: info.name.clone(), message: e.to_string() })?;
        let kernels = Kernels::compile(&device);
        Ok(Self { device, queue, info, kernels })
    }

    pub(crate) fn device(&self) -> &wgpu::Device {
        &self.device
    }

    /// The adapter in words: name, type, API and its largest buffer.
    pub fn describe(&self) -> String {
        let mib = self.largest_buffer() >> 20;
        format!("{} ({:?}, {:?}, buffers up to {mib} MiB)", self.info.name, self.info.device_type, self.info.backend)
    }

    /// Render several Gaussian sets as one scene on the pixels `region` =
    /// [x0, y0, x1, y1) of `camera`'s image (as [`super::render_sets`]); an
    /// error when a buffer the render or its backward pass needs is larger than
    /// the device allows (nothing is sent to the device then).
    pub fn render_sets(
        &self,
        sets: &[&GaussianSet],
        camera: &Camera,
        region: [u32; 4],
        options: &RenderOptions,
    ) -> Result<GpuRender, GpuLimit> {
        let prep = Prepared::new(sets, camera, region, options);
        let projection = prep.projection;
        let (width, height) = (projection.width, projection.height);
        let (tiles_x, tiles_y) = (width.div_ceil(TILE), height.div_ceil(TILE));
        let set_sizes: Vec<usize> = sets.iter().map(|s| s.len()).collect();
        let n: usize = set_sizes.iter().sum();
        let count = u32::try_from(n).expect("at most 2^32 Gaussians");
        let background = match prep.background_pixels {
            Some(img) => BackgroundPixels::Image(img),
            None => BackgroundPixels::Uniform(options.background),
        };
        let flat_params = param_buffer(sets);
        let pixels = u64::from(width) * u64::from(height);
        // The largest buffers of this render and of its backward pass.
        self.fits(&[
            ("parameters and their gradients", 4 * flat_params.len() as u64),
            ("projected Gaussians and their gradients", 4 * SPLAT_STRIDE.max(GRAD_STRIDE as u64) * n as u64),
            ("per-pixel state", 16 * pixels),
        ])?;
        let uniform = frame_uniform(sets, &projection, prep.sh_degree, &background, [tiles_x, tiles_y]);
        let frame = self.uniform(&uniform);
        let params = self.storage_init("params", bytemuck::cast_slice(&flat_params));

        // Project, sort by depth, and count each rank's tiles.
        let mut enc = self.encoder();
        let splats = self.storage("splats", SPLAT_STRIDE * 4 * n as u64);
        let tile_spans = self.storage("tile spans", 16 * n as u64);
        let tile_counts = self.storage("tile counts", 4 * n as u64);
        let depth_keys = self.storage("depth keys", 4 * n as u64);
        let depth_values = self.storage("depth order", 4 * n as u64);
        self.dispatch_1d(
            &mut enc,
            &self.kernels.project,
            &[&frame, &params, &splats, &tile_spans, &tile_counts, &depth_keys, &depth_values],
            count,
        );
        let (_, depth_order) = self.sort_pairs(&mut enc, depth_keys, depth_values, count, 32);
        // One slot more than there are Gaussians: after the scan it holds the total.
        let rank_offsets = self.storage("rank offsets", 4 * (n as u64 + 1));
        self.dispatch_bound(
            &mut enc,
            &self.kernels.counts_by_rank,
            &[(0, &frame), (1, &depth_order), (2, &tile_counts), (3, &rank_offsets)],
            groups_1d(count),
        );
        self.scan(&mut enc, &rank_offsets, count + 1);
        let total = self.read_u32s(enc, &[(&rank_offsets, n as u64, 1)]).remove(0)[0];
        self.fits(&[("tile intersections", 4 * u64::from(total))])?;

        // Intersections sorted by tile, each tile's range, compositing.
        let mut enc = self.encoder();
        let tile_keys = self.storage("tile keys", 4 * total as u64);
        let tile_values = self.storage("tile values", 4 * total as u64);
        self.dispatch_bound(
            &mut enc,
            &self.kernels.emit_intersections,
            &[(0, &frame), (1, &depth_order), (3, &rank_offsets), (4, &tile_spans), (5, &tile_keys), (6, &tile_values)],
            groups_1d(count),
        );
        let tiles = tiles_x * tiles_y;
        let tile_bits = u32::BITS - (tiles - 1).leading_zeros();
        let (tile_keys, tile_values) = self.sort_pairs(&mut enc, tile_keys, tile_values, total, tile_bits);
        let ranges = self.storage("tile ranges", 8 * tiles as u64);
        let pass = self.uniform(&PassUniform { count: total, shift: 0, blocks: 0, unused: 0 });
        self.dispatch_bound(
            &mut enc,
            &self.kernels.tile_ranges,
            &[(0, &pass), (1, &tile_keys), (2, &ranges)],
            groups_1d(total),
        );
        let background_image = match &background {
            BackgroundPixels::Image(img) => self.storage_init("background", bytemuck::cast_slice(img)),
            BackgroundPixels::Uniform(_) => self.storage("background", 4),
        };
        let color = self.storage("colour", 12 * pixels);
        let state = self.storage("pixel state", 16 * pixels);
        self.dispatch_bound(
            &mut enc,
            &self.kernels.rasterize,
            &[
                (0, &frame),
                (1, &splats),
                (2, &depth_order),
                (3, &tile_values),
                (4, &ranges),
                (5, &background_image),
                (6, &color),
                (7, &state),
            ],
            (tiles_x, tiles_y),
        );
        let mut out = self.read_f32s(enc, &[(&color, 0, 3 * pixels), (&state, 0, 4 * pixels)]);
        let state_values = out.pop().expect("two buffers read");
        let color_values = out.pop().expect("two buffers read");
        let mut image = RasterOutput { color: color_values, ..Default::default() };
        for s in state_values.chunks_exact(4) {
            image.alpha.push(s[0]);
            image.depth.push(s[1]);
            image.final_t.push(s[2]);
            image.last.push(s[3] as u32);
        }
        Ok(GpuRender {
            width,
            height,
            image,
            set_sizes,
            background,
            frame,
            params,
            splats,
            tile_counts,
            depth_order,
            tile_values,
            ranges,
            state,
        })
    }

    /// Backward pass of `fwd` (a render of `gs`): as [`super::backward`].
    pub fn backward(
        &self,
        gs: &GaussianSet,
        fwd: &GpuRender,
        grad_color: &[f32],
        grad_alpha: Option<&[f32]>,
        grad_depth: Option<&[f32]>,
    ) -> Gradients {
        self.backward_sets(&[gs], fwd, grad_color, grad_alpha, grad_depth).pop().expect("one set")
    }

    /// Backward pass of a [`Self::render_sets`] render: one [`Gradients`] per set
    /// (as [`super::backward_sets`]).
    pub fn backward_sets(
        &self,
        sets: &[&GaussianSet],
        fwd: &GpuRender,
        grad_color: &[f32],
        grad_alpha: Option<&[f32]>,
        grad_depth: Option<&[f32]>,
    ) -> Vec<Gradients> {
        let sizes: Vec<usize> = sets.iter().map(|s| s.len()).collect();
        assert_eq!(sizes, fwd.set_sizes, "the backward pass needs the rendered Gaussian sets");
        let n: usize = sizes.iter().sum();
        let pixels = (fwd.width * fwd.height) as usize;
        assert_eq!(grad_color.len(), 3 * pixels, "colour gradient must match the image");
        // Per pixel what the kernel reads, and the background's gradient, which is
        // the colour gradient times the final transmittance.
        let mut pixel_grads = Vec::with_capacity(6 * pixels);
        let mut background = Vec3::ZERO;
        for o in 0..pixels {
            let tf = fwd.image.final_t[o];
            let gc = Vec3::from_slice(&grad_color[3 * o..3 * o + 3]);
            pixel_grads.extend_from_slice(&gc.to_array());
            pixel_grads.push(grad_alpha.map_or(0.0, |a| a[o]) * tf);
            pixel_grads.push(grad_depth.map_or(0.0, |d| d[o]));
            pixel_grads.push(gc.dot(fwd.background.at(o)) * tf);
            background += gc * tf;
        }
        let pixel_grads = self.storage_init("pixel gradients", bytemuck::cast_slice(&pixel_grads));
        let projected_grads = self.storage("projected gradients", (4 * GRAD_STRIDE * n) as u64);
        let mut enc = self.encoder();
        let (tiles_x, tiles_y) = (fwd.width.div_ceil(TILE), fwd.height.div_ceil(TILE));
        self.dispatch_bound(
            &mut enc,
            &self.kernels.rasterize_backward,
            &[
                (0, &fwd.frame),
                (1, &fwd.splats),
                (2, &fwd.depth_order),
                (3, &fwd.tile_values),
                (4, &fwd.ranges),
                (5, &fwd.state),
                (6, &pixel_grads),
                (7, &projected_grads),
            ],
            (tiles_x, tiles_y),
        );
        let param_floats = fwd.params.size() / 4;
        let param_grads = self.storage("parameter gradients", 4 * param_floats);
        let screen_stats = self.storage("screen statistics", 12 * n as u64);
        self.dispatch_1d(
            &mut enc,
            &self.kernels.project_backward,
            &[&fwd.frame, &fwd.params, &fwd.splats, &fwd.tile_counts, &projected_grads, &param_grads, &screen_stats],
            n as u32,
        );
        let mut out = self.read_f32s(enc, &[(&param_grads, 0, param_floats), (&screen_stats, 0, 3 * n as u64)]);
        let stats = out.pop().expect("two buffers read");
        let flat = out.pop().expect("two buffers read");
        // Each group's block holds the sets one after another.
        let mut grads: Vec<Gradients> = sets
            .iter()
            .map(|gs| Gradients {
                params: GaussianSet::new(gs.sh_degree),
                background,
                mean2d_grad_norm: Vec::with_capacity(gs.len()),
                visible: Vec::with_capacity(gs.len()),
                radius: Vec::with_capacity(gs.len()),
            })
            .collect();
        let mut rest: &[f32] = &flat;
        for group in ParamGroup::ALL {
            for (g, gs) in grads.iter_mut().zip(sets) {
                let len = gs.width(group) * gs.len();
                *g.params.group_mut(group) = rest[..len].to_vec();
                rest = &rest[len..];
            }
        }
        let mut stats = stats.chunks_exact(3);
        for (g, gs) in grads.iter_mut().zip(sets) {
            for v in stats.by_ref().take(gs.len()) {
                g.mean2d_grad_norm.push(v[0]);
                g.visible.push(v[1] > 0.5);
                g.radius.push(v[2]);
            }
        }
        grads
    }

    /// Whether buffers of these sizes (bytes, with what they hold) fit the
    /// device's largest storage buffer.
    fn fits(&self, buffers: &[(&'static str, u64)]) -> Result<(), GpuLimit> {
        check_buffer_sizes(buffers, self.largest_buffer())
    }

    /// The largest storage buffer the device allows, in bytes.
    pub fn largest_buffer(&self) -> u64 {
        let limits = self.device.limits();
        limits.max_buffer_size.min(limits.max_storage_buffer_binding_size)
    }

    pub(crate) fn encoder(&self) -> wgpu::CommandEncoder {
        self.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None })
    }

    pub(crate) fn uniform<T: Pod>(&self, value: &T) -> wgpu::Buffer {
        self.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: None,
            contents: bytemuck::bytes_of(value),
            usage: wgpu::BufferUsages::UNIFORM,
        })
    }

    /// A zeroed storage buffer of `bytes` (at least one word: bindings cannot be empty).
    pub(crate) fn storage(&self, label: &str, bytes: u64) -> wgpu::Buffer {
        self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size: bytes.max(4).next_multiple_of(4),
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        })
    }

    pub(crate) fn storage_init(&self, label: &str, contents: &[u8]) -> wgpu::Buffer {
        if contents.is_empty() {
            return self.storage(label, 4);
        }
        self.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some(label),
            contents,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
        })
    }

    /// Dispatch a 1D kernel over `count` threads whose bindings are 0, 1, 2, ... in order.
    fn dispatch_1d(
        &self,
        enc: &mut wgpu::CommandEncoder,
        kernel: &wgpu::ComputePipeline,
        buffers: &[&wgpu::Buffer],
        count: u32,
    ) {
        let bound: Vec<(u32, &wgpu::Buffer)> = buffers.iter().enumerate().map(|(i, b)| (i as u32, *b)).collect();
        self.dispatch_bound(enc, kernel, &bound, groups_1d(count));
    }

    pub(crate) fn dispatch_bound(
        &self,
        enc: &mut wgpu::CommandEncoder,
        kernel: &wgpu::ComputePipeline,
        buffers: &[(u32, &wgpu::Buffer)],
        groups: (u32, u32),
    ) {
        if groups.0 == 0 || groups.1 == 0 {
            return;
        }
        let entries: Vec<wgpu::BindGroupEntry> = buffers
            .iter()
            .map(|(binding, buffer)| wgpu::BindGroupEntry { binding: *binding, resource: buffer.as_entire_binding() })
            .collect();
        let bind_group = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: None,
            layout: &kernel.get_bind_group_layout(0),
            entries: &entries,
        });
        let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor { label: None, timestamp_writes: None });
        pass.set_pipeline(kernel);
        pass.set_bind_group(0, &bind_group, &[]);
        pass.dispatch_workgroups(groups.0, groups.1, 1);
    }

    /// Stable sort of `count` (key, value) pairs on the low `bits` bits of the
    /// keys, 8 bits a pass; returns the buffers holding the sorted pairs.
    fn sort_pairs(
        &self,
        enc: &mut wgpu::CommandEncoder,
        keys: wgpu::Buffer,
        values: wgpu::Buffer,
        count: u32,
        bits: u32,
    ) -> (wgpu::Buffer, wgpu::Buffer) {
        let blocks = count.div_ceil(GROUP);
        let block_counts = self.storage("digit counts", 4 * 256 * blocks as u64);
        let mut from = (keys, values);
        let mut to = (self.storage("sort keys", 4 * count as u64), self.storage("sort values", 4 * count as u64));
        for shift in (0..bits).step_by(8) {
            let pass = self.uniform(&PassUniform { count, shift, blocks, unused: 0 });
            self.dispatch_bound(
                enc,
                &self.kernels.count_digits,
                &[(0, &pass), (1, &from.0), (3, &block_counts)],
                groups_1d(count),
            );
            self.scan(enc, &block_counts, 256 * blocks);
            self.dispatch_bound(
                enc,
                &self.kernels.scatter,
                &[(0, &pass), (1, &from.0), (2, &from.1), (3, &block_counts), (4, &to.0), (5, &to.1)],
                groups_1d(count),
            );
            std::mem::swap(&mut from, &mut to);
        }
        from
    }

    /// Exclusive prefix sum of the first `count` u32s of `data`, in place.
    fn scan(&self, enc: &mut wgpu::CommandEncoder, data: &wgpu::Buffer, count: u32) {
        let blocks = count.div_ceil(GROUP);
        let sums = self.storage("block sums", 4 * blocks as u64);
        let pass = self.uniform(&PassUniform { count, shift: 0, blocks, unused: 0 });
        self.dispatch_bound(enc, &self.kernels.scan_blocks, &[(0, &pass), (1, data), (2, &sums)], groups_1d(count));
        if blocks > 1 {
            self.scan(enc, &sums, blocks);
            self.dispatch_bound(
                enc,
                &self.kernels.add_block_offsets,
                &[(0, &pass), (1, data), (2, &sums)],
                groups_1d(count),
            );
        }
    }

    /// Submit `enc` after copying (buffer, first word, words) ranges out, and
    /// read them back.
    fn read_words(&self, mut enc: wgpu::CommandEncoder, ranges: &[(&wgpu::Buffer, u64, u64)]) -> Vec<Vec<u8>> {
        let staging: Vec<wgpu::Buffer> = ranges
            .iter()
            .map(|&(buffer, first, words)| {
                let size = (4 * words).max(4);
                let s = self.device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some("read back"),
                    size,
                    usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                    mapped_at_creation: false,
                });
                if words > 0 {
                    enc.copy_buffer_to_buffer(buffer, 4 * first, &s, 0, 4 * words);
                }
                s
            })
            .collect();
        self.queue.submit([enc.finish()]);
        for s in &staging {
            s.slice(..).map_async(wgpu::MapMode::Read, |r| r.expect("mapping a read-back buffer"));
        }
        self.device.poll(wgpu::PollType::wait_indefinitely()).expect("waiting for the GPU");
        staging
            .iter()
            .zip(ranges)
            .map(|(s, &(_, _, words))| {
                let bytes =
                    s.slice(..).get_mapped_range().expect("mapped read-back buffer")[..4 * words as usize].to_vec();
                s.unmap();
                bytes
            })
            .collect()
    }

    fn read_u32s(&self, enc: wgpu::CommandEncoder, ranges: &[(&wgpu::Buffer, u64, u64)]) -> Vec<Vec<u32>> {
        self.read_words(enc, ranges).into_iter().map(|b| bytemuck::cast_slice(&b).to_vec()).collect()
    }

    pub(crate) fn read_f32s(&self, enc: wgpu::CommandEncoder, ranges: &[(&wgpu::Buffer, u64, u64)]) -> Vec<Vec<f32>> {
        self.read_words(enc, ranges).into_iter().map(|b| bytemuck::cast_slice(&b).to_vec()).collect()
    }
}

/// Workgroups for `count` threads of a 256-wide 1D kernel, as a 2D grid.
pub(crate) fn groups_1d(count: u32) -> (u32, u32) {
    let blocks = count.div_ceil(GROUP);
    if blocks == 0 {
        return (0, 0);
    }
    let x = blocks.min(MAX_GROUPS_PER_DIM);
    (x, blocks.div_ceil(x))
}

/// The sets' parameter groups one after another, in [`ParamGroup::ALL`] order,
/// each group holding the sets one after another: the layout of one set that
/// holds them all.
fn param_buffer(sets: &[&GaussianSet]) -> Vec<f32> {
    let mut flat = Vec::with_capacity(sets.iter().flat_map(|gs| ParamGroup::ALL.map(|g| gs.group(g).len())).sum());
    for group in ParamGroup::ALL {
        for gs in sets {
            flat.extend_from_slice(gs.group(group));
        }
    }
    flat
}

fn frame_uniform(
    sets: &[&GaussianSet],
    cam: &ProjectionCamera,
    sh_degree: u32,
    background: &BackgroundPixels,
    [tiles_x, tiles_y]: [u32; 2],
) -> FrameUniform {
    let n: usize = sets.iter().map(|s| s.len()).sum();
    // The sets share an SH degree (Prepared::new checks), so one set's widths are all's.
    let widths = sets[0];
    let mut offsets = [0u32; 6];
    let mut at = 0usize;
    for (slot, group) in ParamGroup::ALL.iter().enumerate() {
        offsets[slot] = u32::try_from(at).expect("parameters fit 32-bit offsets");
        at += widths.width(*group) * n;
    }
    let (lim_x, lim_y) = cam.limits();
    // w = 1: the kernel reads the per-pixel background image instead.
    let background = match background {
        BackgroundPixels::Uniform(c) => c.extend(0.0),
        BackgroundPixels::Image(_) => glam::Vec4::new(0.0, 0.0, 0.0, 1.0),
    };
    FrameUniform {
        rotation: [
            cam.rot.x_axis.extend(0.0).into(),
            cam.rot.y_axis.extend(0.0).into(),
            cam.rot.z_axis.extend(0.0).into(),
        ],
        translation: cam.trans.extend(0.0).into(),
        position: cam.position.extend(0.0).into(),
        intrinsics: [cam.fx, cam.fy, cam.cx, cam.cy],
        limits: [lim_x, lim_y, 0.0, 0.0],
        background: background.into(),
        image: [cam.width, cam.height, tiles_x, tiles_y],
        sizes: [n as u32, sh_degree, widths.width(ParamGroup::ShRest) as u32, 0],
        offsets: [offsets[0], offsets[1], offsets[2], offsets[3]],
        offsets2: [offsets[4], offsets[5], 0, 0],
    }
}

/// A WGSL module compiled for `device` from `parts` put one after another (a
/// kernel's file after the shared ones it uses: common.wgsl, gaussian.wgsl, sh.wgsl).
pub(crate) fn shader_module(device: &wgpu::Device, name: &str, parts: &[&str]) -> wgpu::ShaderModule {
    device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some(name),
        source: wgpu::ShaderSource::Wgsl(parts.concat().into()),
    })
}

/// The compute pipeline of `module`'s entry point `entry`, its bind group
/// layout derived from what the entry point uses.
pub(crate) fn compute_pipeline(
    device: &wgpu::Device,
    module: &wgpu::ShaderModule,
    entry: &str,
) -> wgpu::ComputePipeline {
    device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
        label: Some(entry),
        layout: None,
        module,
        entry_point: Some(entry),
        compilation_options: Default::default(),
        cache: None,
    })
}

impl Kernels {
    fn compile(device: &wgpu::Device) -> Self {
        const GAUSSIAN: &str = include_str!("../../shaders/gaussian.wgsl");
        const SH: &str = include_str!("../../shaders/sh.wgsl");
        let module = |name: &str, parts: &[&str]| shader_module(device, name, parts);
        let pipeline = |module: &wgpu::ShaderModule, entry: &str| compute_pipeline(device, module, entry);
        let project = module("project", &[COMMON_WGSL, GAUSSIAN, SH, include_str!("../../shaders/project.wgsl")]);
        let sort = module("sort", &[COMMON_WGSL, include_str!("../../shaders/sort.wgsl")]);
        let scan = module("scan", &[COMMON_WGSL, include_str!("../../shaders/scan.wgsl")]);
        let bin = module("bin", &[COMMON_WGSL, include_str!("../../shaders/bin.wgsl")]);
        let ranges = module("tile ranges", &[COMMON_WGSL, include_str!("../../shaders/tile_ranges.wgsl")]);
        let raster = module("rasterize", &[COMMON_WGSL, include_str!("../../shaders/rasterize.wgsl")]);
        let raster_bwd =
            module("rasterize backward", &[COMMON_WGSL, include_str!("../../shaders/rasterize_backward.wgsl")]);
        let project_bwd = module(
            "project backward",
            &[COMMON_WGSL, GAUSSIAN, SH, include_str!("../../shaders/project_backward.wgsl")],
        );
        Self {
            project: pipeline(&project, "main"),
            count_digits: pipeline(&sort, "count_digits"),
            scatter: pipeline(&sort, "scatter"),
            scan_blocks: pipeline(&scan, "scan_blocks"),
            add_block_offsets: pipeline(&scan, "add_block_offsets"),
            counts_by_rank: pipeline(&bin, "counts_by_rank"),
            emit_intersections: pipeline(&bin, "emit_intersections"),
            tile_ranges: pipeline(&ranges, "main"),
            rasterize: pipeline(&raster, "main"),
            rasterize_backward: pipeline(&raster_bwd, "main"),
            project_backward: pipeline(&project_bwd, "main"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_first_buffer_over_the_limit_is_named() {
        let buffers = [("small", 10), ("large", 300), ("larger", 400)];
        assert!(check_buffer_sizes(&buffers, 400).is_ok());
        let err = check_buffer_sizes(&buffers, 299).expect_err("over");
        assert_eq!((err.what, err.bytes, err.limit), ("large", 300, 299));
        assert_eq!(err.to_string(), "large need 300 bytes on the GPU, more than its largest buffer (299 bytes)");
    }
}
