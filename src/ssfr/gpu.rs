//! The screen-space passes on the GPU: `shaders/ssfr.wgsl`, compute passes one invocation per
//! pixel, each the CPU reference's per-pixel function ([`super::cpu`], the specification) over
//! the same inputs: the spheres and the projected thickness Gaussians binned into the same
//! 16x16 tiles on the host, in storage buffers. The filters ping-pong between two depth
//! buffers; the shading after the read-back is the CPU's (`splat::shade`), as for the ray
//! caster. Tests compare every pass with the CPU's.

use wgpu::util::DeviceExt;

use super::cpu::{ScreenSpace, SsfrRender, SsfrTimings, depth_image, project_sources};
use super::{DepthFilter, FilterScales, SsfrError};
use crate::gpu::{GpuContext, GpuError};
use crate::raycast::cpu::bin;
use crate::splat::{Render, View};

/// The WGSL source of the passes.
pub const SHADER: &str = include_str!("../../shaders/ssfr.wgsl");

/// The uniforms of the passes (`Params` in the WGSL, 160 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct RawSsfrParams {
    pub inv_view: [[f32; 4]; 4],
    /// width, height, tan_half.x, tan_half.y
    pub screen: [f32; 4],
    /// orthographic (0/1), tiles along x, filter half width, -
    pub a: [u32; 4],
    /// sigma_px, sigma_depth, range, clamp (world units)
    pub b: [f32; 4],
    /// curvature step, pixel size at depth 1, thickness sigma (world), -
    pub c: [f32; 4],
    /// the water's colour before the tint (rgb)
    pub base: [f32; 4],
    /// absorption per world length (rgb)
    pub absorb: [f32; 4],
}

const _: () = assert!(std::mem::size_of::<RawSsfrParams>() == 160);

/// No fluid (`NONE` in the WGSL; the CPU's infinity).
const NONE: f32 = 1e30;

/// Most items a tile's list may hold: llvmpipe ends an invocation's loops after 65,535
/// iterations in total, so a longer list would be cut silently there.
pub const MAX_TILE_ITEMS: usize = 60_000;

/// The compiled passes, made once and used for any number of frames and views.
pub struct GpuSsfr {
    depth: wgpu::ComputePipeline,
    filters: [wgpu::ComputePipeline; 4],
    thickness: wgpu::ComputePipeline,
    thickness_filter: wgpu::ComputePipeline,
    shade: wgpu::ComputePipeline,
}

/// The tile lists as compressed rows: `starts[t]..starts[t + 1]` index `items`.
fn csr(tiles: &[Vec<u32>]) -> Result<(Vec<u32>, Vec<u32>), SsfrError> {
    let mut starts = Vec::with_capacity(tiles.len() + 1);
    let mut items = Vec::new();
    for t in tiles {
        if t.len() > MAX_TILE_ITEMS {
            return Err(SsfrError::TooDense {
                items: t.len(),
                limit: MAX_TILE_ITEMS,
            });
        }
        starts.push(items.len() as u32);
        items.extend_from_slice(t);
    }
    starts.push(items.len() as u32);
    Ok((starts, items))
}

impl GpuSsfr {
    /// Compiles the passes.
    pub fn new(device: &wgpu::Device) -> Result<Self, GpuError> {
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("ssfr"),
            source: wgpu::ShaderSource::Wgsl(SHADER.into()),
        });
        let pipeline = |entry| {
            device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(entry),
                layout: None,
                module: &module,
                entry_point: Some(entry),
                compilation_options: Default::default(),
                cache: None,
            })
        };
        let passes = Self {
            depth: pipeline("cs_depth"),
            filters: [
                pipeline("cs_narrow_range"),
                pipeline("cs_bilateral"),
                pipeline("cs_plane"),
                pipeline("cs_curvature_flow"),
            ],
            thickness: pipeline("cs_thickness"),
            thickness_filter: pipeline("cs_thickness_filter"),
            shade: pipeline("cs_shade"),
        };
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Validation(e.to_string()));
        }
        Ok(passes)
    }

    /// Every pass of `screen` from view `v`, read back: the same buffers as
    /// [`ScreenSpace::render_view`] (the timings are not split by pass: `depth_ms` holds the
    /// whole GPU run with its read-back).
    pub fn render(
        &self,
        ctx: &GpuContext,
        screen: &ScreenSpace<'_>,
        v: &View,
    ) -> Result<SsfrRender, crate::Error> {
        let t = std::time::Instant::now();
        let device = &ctx.device;
        let params = screen.params();
        let (w, h) = (v.width, v.height);
        let pixels = u64::from(w) * u64::from(h);
        // the host's part, as the CPU does it
        let spheres: Vec<[f32; 4]> = (0..screen.drawn())
            .map(|k| {
                let (c, r) = screen.sphere_of(k);
                [c.x, c.y, c.z, r]
            })
            .collect();
        let (tw, tiles) =
            bin(v, spheres.len(), |k| screen.sphere_of(k)).map_err(SsfrError::from)?;
        let (tile_starts, tile_items) = csr(&tiles)?;
        let sources = screen.sources();
        let projected: Vec<[f32; 4]> = project_sources(v, sources)
            .into_iter()
            .map(|p| p.map_or([0.0; 4], |(c, k2, a)| [c.x, c.y, k2, a]))
            .collect();
        let (_, source_tiles) = bin(v, sources.len(), |k| {
            (sources[k].centre, 3.0 * sources[k].sigma)
        })
        .map_err(SsfrError::from)?;
        let (source_starts, source_items) = csr(&source_tiles)?;
        let scales = FilterScales::of(params, screen.sphere());
        let image = depth_image(v, Vec::new());
        let absorb = glam::Vec3::from(params.absorption) / screen.reference_radius();
        let uniforms = RawSsfrParams {
            inv_view: v.inv_view.to_cols_array_2d(),
            screen: [w as f32, h as f32, v.tan_half.x, v.tan_half.y],
            a: [
                u32::from(v.is_orthographic()),
                tw as u32,
                scales.radius_px,
                0,
            ],
            b: [
                scales.sigma_px,
                scales.sigma_depth,
                scales.range,
                scales.clamp,
            ],
            c: [
                scales.step,
                image.pixel_size,
                params.thickness_sigma_range * screen.reference_radius(),
                0.0,
            ],
            base: crate::splat::WATER,
            absorb: absorb.extend(0.0).to_array(),
        };
        // buffers
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let storage = wgpu::BufferUsages::STORAGE;
        let init = |label, contents: &[u8]| {
            let padded;
            let contents = if contents.is_empty() {
                padded = [0u8; 16];
                &padded[..]
            } else {
                contents
            };
            device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents,
                usage: storage,
            })
        };
        let work = |label| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: (4 * pixels).max(16),
                usage: storage | wgpu::BufferUsages::COPY_SRC | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            })
        };
        let uniform = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("ssfr params"),
            contents: bytemuck::bytes_of(&uniforms),
            usage: wgpu::BufferUsages::UNIFORM,
        });
        let sphere_buf = init("ssfr spheres", bytemuck::cast_slice(&spheres));
        let tile_starts = init("ssfr tile starts", bytemuck::cast_slice(&tile_starts));
        let tile_items = init("ssfr tile items", bytemuck::cast_slice(&tile_items));
        let source_buf = init("ssfr sources", bytemuck::cast_slice(&projected));
        let source_starts = init("ssfr source starts", bytemuck::cast_slice(&source_starts));
        let source_items = init("ssfr source items", bytemuck::cast_slice(&source_items));
        let depth = [work("ssfr depth a"), work("ssfr depth b")];
        let raw = work("ssfr raw depth");
        let thick_raw = work("ssfr raw thickness");
        let thick = work("ssfr thickness");
        let wide = |label| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: (16 * pixels).max(16),
                usage: storage | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            })
        };
        let colour = wide("ssfr colour");
        let normal_depth = wide("ssfr normal and depth");
        let group = |pipeline: &wgpu::ComputePipeline, entries: &[(u32, &wgpu::Buffer)]| {
            let entries: Vec<wgpu::BindGroupEntry<'_>> = entries
                .iter()
                .map(|&(binding, b)| wgpu::BindGroupEntry {
                    binding,
                    resource: b.as_entire_binding(),
                })
                .collect();
            device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: None,
                layout: &pipeline.get_bind_group_layout(0),
                entries: &entries,
            })
        };
        let depth_group = group(
            &self.depth,
            &[
                (0, &uniform),
                (1, &sphere_buf),
                (2, &tile_starts),
                (3, &tile_items),
                (6, &depth[0]),
            ],
        );
        let iterations = params.filter_iterations() as usize;
        let filter = match params.filter {
            DepthFilter::NarrowRange => Some(&self.filters[0]),
            DepthFilter::Bilateral => Some(&self.filters[1]),
            DepthFilter::Plane => Some(&self.filters[2]),
            DepthFilter::CurvatureFlow => Some(&self.filters[3]),
            DepthFilter::None => None,
        };
        let filter_groups = filter.map(|f| {
            [
                group(f, &[(0, &uniform), (5, &depth[0]), (6, &depth[1])]),
                group(f, &[(0, &uniform), (5, &depth[1]), (6, &depth[0])]),
            ]
        });
        // after the iterations the filtered depth is in depth[iterations % 2]
        let last = if filter.is_some() { iterations % 2 } else { 0 };
        let thickness_group = group(
            &self.thickness,
            &[
                (0, &uniform),
                (2, &source_starts),
                (3, &source_items),
                (4, &source_buf),
                (6, &thick_raw),
            ],
        );
        let thickness_filter_group = group(
            &self.thickness_filter,
            &[
                (0, &uniform),
                (5, &depth[last]),
                (6, &thick),
                (7, &thick_raw),
            ],
        );
        let shade_group = group(
            &self.shade,
            &[
                (0, &uniform),
                (5, &depth[last]),
                (7, &thick),
                (8, &colour),
                (9, &normal_depth),
            ],
        );
        let groups = (w.div_ceil(8), h.div_ceil(8));
        let mut encoder = device.create_command_encoder(&Default::default());
        {
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.depth);
            pass.set_bind_group(0, &depth_group, &[]);
            pass.dispatch_workgroups(groups.0, groups.1, 1);
        }
        encoder.copy_buffer_to_buffer(&depth[0], 0, &raw, 0, raw.size());
        {
            let mut pass = encoder.begin_compute_pass(&Default::default());
            if let (Some(f), Some(g)) = (filter, &filter_groups) {
                pass.set_pipeline(f);
                for k in 0..iterations {
                    pass.set_bind_group(0, &g[k % 2], &[]);
                    pass.dispatch_workgroups(groups.0, groups.1, 1);
                }
            }
            pass.set_pipeline(&self.thickness);
            pass.set_bind_group(0, &thickness_group, &[]);
            pass.dispatch_workgroups(groups.0, groups.1, 1);
            pass.set_pipeline(&self.thickness_filter);
            pass.set_bind_group(0, &thickness_filter_group, &[]);
            pass.dispatch_workgroups(groups.0, groups.1, 1);
            pass.set_pipeline(&self.shade);
            pass.set_bind_group(0, &shade_group, &[]);
            pass.dispatch_workgroups(groups.0, groups.1, 1);
        }
        ctx.queue.submit([encoder.finish()]);
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Validation(e.to_string()).into());
        }
        let depths = |b: &wgpu::Buffer| -> Result<Vec<f32>, GpuError> {
            let d: Vec<f32> = crate::gpu::read_buffer(ctx, b)?;
            Ok(d[..pixels as usize]
                .iter()
                .map(|&z| if z >= NONE { f32::INFINITY } else { z })
                .collect())
        };
        let raw_depth = depths(&raw)?;
        let filtered = depths(&depth[last])?;
        let thickness: Vec<f32> = crate::gpu::read_buffer(ctx, &thick)?;
        let wide_of = |b: &wgpu::Buffer| -> Result<Vec<[f32; 4]>, GpuError> {
            let d: Vec<[f32; 4]> = crate::gpu::read_buffer(ctx, b)?;
            Ok(d[..pixels as usize].to_vec())
        };
        let colour = wide_of(&colour)?;
        let normal_depth = wide_of(&normal_depth)?;
        let shaded = crate::splat::cpu::shade_image(&colour, &normal_depth, v);
        Ok(SsfrRender {
            render: Render {
                width: w,
                height: h,
                image: shaded,
                colour,
                normal_depth,
            },
            raw_depth,
            depth: filtered,
            thickness: thickness[..pixels as usize].to_vec(),
            timings: SsfrTimings {
                depth_ms: t.elapsed().as_secs_f64() * 1e3,
                ..Default::default()
            },
        })
    }
}

/// Every screen-space pass of `screen` from view `v` on the GPU (compiles the passes; keep a
/// [`GpuSsfr`] to draw many).
pub fn render_view_gpu(
    ctx: &GpuContext,
    screen: &ScreenSpace<'_>,
    v: &View,
) -> Result<SsfrRender, crate::Error> {
    GpuSsfr::new(&ctx.device)?.render(ctx, screen, v)
}
