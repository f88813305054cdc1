//! The optics stage on the GPU (`shaders/optics.wgsl`, `shaders/optics_geometry.wgsl`): caustics
//! through illumination volumes and the final image, tested against the CPU reference of
//! [`crate::optics`].
//!
//! [`OpticsGpu::prepare`] creates every target and buffer for one stage (the light's splatting,
//! the geometry maps, the caustics map, the camera's splatting and the image) on the given device;
//! [`PreparedOptics::encode_caustics`] and [`PreparedOptics::encode_frame`] record the passes into
//! the caller's encoder, and [`PreparedOptics::read`] copies the results back. [`render_gpu`] does
//! all of it headless.

use std::time::Instant;

use glam::{Vec3, Vec4};
use image::RgbaImage;
use serde::Serialize;
use wgpu::util::DeviceExt;

use crate::gpu::{self, GpuContext, GpuError, entry, texture_2d, texture_descriptor};
use crate::optics::{Container, EnvironmentKind, LightKind, OpticsError, Stage, encode};
use crate::splat::{GpuWaterPass, Light, Surfel, View, WaterSurface};

/// The WGSL of the caustics and final-image passes.
pub const SHADER: &str = concat!(
    include_str!("../../shaders/common.wgsl"),
    include_str!("../../shaders/optics.wgsl")
);
/// The WGSL of the geometry-map pass.
pub const GEOMETRY_SHADER: &str = concat!(
    include_str!("../../shaders/common.wgsl"),
    include_str!("../../shaders/optics_geometry.wgsl")
);

const FLOAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba32Float;
const DEPTH: wgpu::TextureFormat = wgpu::TextureFormat::Depth32Float;

/// A view as the shader reads it (`ViewU`, 224 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct RawView {
    pub view: [[f32; 4]; 4],
    pub inv_view: [[f32; 4]; 4],
    pub proj: [[f32; 4]; 4],
    pub viewport: [f32; 2],
    pub tan_half: [f32; 2],
    pub flags: [f32; 4],
}

impl RawView {
    fn of(v: &View) -> Self {
        let (view, inv_view, proj) = v.matrices();
        Self {
            view: view.to_cols_array_2d(),
            inv_view: inv_view.to_cols_array_2d(),
            proj: proj.to_cols_array_2d(),
            viewport: [v.width as f32, v.height as f32],
            tan_half: v.half_extent().to_array(),
            flags: [f32::from(u8::from(v.is_orthographic())), 0.0, 0.0, 0.0],
        }
    }
}

/// The optics uniforms (`Uniforms` in optics.wgsl, 912 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct RawOptics {
    pub screen: RawView,
    pub map: RawView,
    pub camera: RawView,
    pub light_dir: [f32; 4],
    pub light_pos: [f32; 4],
    pub light_colour: [f32; 4],
    pub ambient: [f32; 4],
    pub water: [f32; 4],
    pub extinction: [f32; 4],
    pub albedo: [f32; 4],
    pub env: [f32; 4],
    pub env_colour: [f32; 4],
    pub env_horizon: [f32; 4],
    pub env_zenith: [f32; 4],
    pub env_ground: [f32; 4],
    /// x: the receiver's triangle count when rays meet it exactly (at most
    /// [`EXACT_TRIANGLES`]), 0 when the geometry-map search finds the hits.
    pub exact: [f32; 4],
    /// The receiver's container: `w = 1` an open box (its floor corner and opposite corner),
    /// `w = 2` a closed mesh (its bounds; met with exact rays only: at most
    /// [`EXACT_TRIANGLES`]), 0 none.
    pub container_min: [f32; 4],
    pub container_max: [f32; 4],
}

/// Receivers of at most this many triangles (a plane, an open box, a small mesh) are met by
/// exact rays on the GPU too, tested against every triangle as the CPU's BVH does (the same
/// Möller-Trumbore with the same slack); larger meshes use the paper's geometry-map search
/// (§5.1.2). Measured on the column's splash frame (an open box): the search missed 32 % of the
/// refracted rays that the exact test hits, and put 15 % of the hits it found more than 1 cm off.
pub const EXACT_TRIANGLES: usize = 256;

/// The geometry pass's uniforms (`GeometryU`, 144 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct RawGeometry {
    pub view_proj: [[f32; 4]; 4],
    pub view: [[f32; 4]; 4],
    pub eye: [f32; 4],
}

impl RawGeometry {
    fn of(v: &View) -> Self {
        let (view, inv_view, proj) = v.matrices();
        let eye = if v.is_orthographic() {
            v.forward().extend(1.0)
        } else {
            (inv_view * Vec4::W).truncate().extend(0.0)
        };
        Self {
            view_proj: (proj * view).to_cols_array_2d(),
            view: view.to_cols_array_2d(),
            eye: eye.to_array(),
        }
    }
}

fn raw_optics(stage: &Stage, camera: &View) -> RawOptics {
    let s = &stage.scene;
    let v4 = |v: Vec3, w: f32| v.extend(w).to_array();
    let (light_dir, kind) = match s.light.kind {
        LightKind::Directional => (-s.light.direction.normalize(), 0.0),
        LightKind::Point => (Vec3::ZERO, 1.0),
    };
    let env = &s.environment;
    let (env_kind, ew, eh) = match (env.kind, &env.pixels) {
        (EnvironmentKind::Constant, _) | (EnvironmentKind::Image, None) => (0.0, 1.0, 1.0),
        (EnvironmentKind::Gradient, _) => (1.0, 1.0, 1.0),
        (EnvironmentKind::Image, Some((w, h, _))) => (2.0, *w as f32, *h as f32),
    };
    RawOptics {
        screen: RawView::of(&stage.views.screen),
        map: RawView::of(&stage.views.map),
        camera: RawView::of(camera),
        light_dir: v4(light_dir, kind),
        light_pos: v4(s.light.position, 1.0),
        light_colour: v4(s.light.colour, 0.0),
        ambient: v4(s.light.ambient, 0.0),
        water: [
            s.water.ior,
            s.optics.discontinuity,
            s.optics.tolerance,
            s.optics.max_iterations as f32,
        ],
        extinction: v4(s.water.extinction, stage.size),
        albedo: v4(s.receiver.albedo, s.receiver.checker),
        env: [env_kind, 1e-5 * stage.size, ew, eh],
        env_colour: v4(env.colour, 0.0),
        env_horizon: v4(env.horizon, 0.0),
        env_zenith: v4(env.zenith, 0.0),
        env_ground: v4(env.ground, 0.0),
        exact: [
            if stage.receiver.triangles.len() <= EXACT_TRIANGLES {
                stage.receiver.triangles.len() as f32
            } else {
                0.0
            },
            0.0,
            0.0,
            0.0,
        ],
        container_min: match stage.receiver.container {
            Some(Container::OpenBox { min, .. }) => v4(min, 1.0),
            Some(Container::ClosedMesh) if stage.receiver.triangles.len() <= EXACT_TRIANGLES => {
                v4(stage.receiver.bounds().0, 2.0)
            }
            _ => [0.0; 4],
        },
        container_max: match stage.receiver.container {
            Some(Container::OpenBox { max, .. }) => v4(max, 0.0),
            Some(Container::ClosedMesh) => v4(stage.receiver.bounds().1, 0.0),
            None => [0.0; 4],
        },
    }
}

/// The compiled pipelines of the optics stage.
pub struct OpticsGpu {
    layout: wgpu::BindGroupLayout,
    vertices: wgpu::ComputePipeline,
    triangles: wgpu::ComputePipeline,
    irradiance: wgpu::ComputePipeline,
    frame: wgpu::ComputePipeline,
    geometry_layout: wgpu::BindGroupLayout,
    geometry: wgpu::RenderPipeline,
}

impl OpticsGpu {
    /// Compiles the shaders and builds the pipelines on `device`.
    pub fn new(device: &wgpu::Device) -> Result<Self, GpuError> {
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("optics"),
            source: wgpu::ShaderSource::Wgsl(SHADER.into()),
        });
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("optics"),
            // 0 uniforms; 5, 6, 7, 12, 14 storage buffers; the rest textures (see optics.wgsl)
            entries: &(0..15)
                .map(|b| match b {
                    0 => entry::uniform(b, wgpu::ShaderStages::COMPUTE),
                    5 | 6 | 7 | 12 | 14 => entry::storage(b, wgpu::ShaderStages::COMPUTE),
                    _ => entry::texture(b, wgpu::ShaderStages::COMPUTE),
                })
                .collect::<Vec<_>>(),
        });
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("optics"),
            bind_group_layouts: &[Some(&layout)],
            ..Default::default()
        });
        let compute = |entry: &str| {
            device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(entry),
                layout: Some(&pipeline_layout),
                module: &module,
                entry_point: Some(entry),
                compilation_options: Default::default(),
                cache: None,
            })
        };
        let vertices = compute("cs_vertices");
        let triangles = compute("cs_triangles");
        let irradiance = compute("cs_irradiance");
        let frame = compute("cs_frame");
        let geometry_module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("optics geometry"),
            source: wgpu::ShaderSource::Wgsl(GEOMETRY_SHADER.into()),
        });
        let geometry_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("optics geometry"),
            entries: &[entry::uniform(0, wgpu::ShaderStages::VERTEX_FRAGMENT)],
        });
        let geometry_pipeline_layout =
            device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some("optics geometry"),
                bind_group_layouts: &[Some(&geometry_layout)],
                ..Default::default()
            });
        let target = Some(wgpu::ColorTargetState {
            format: FLOAT,
            blend: None,
            write_mask: wgpu::ColorWrites::ALL,
        });
        let geometry = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
            label: Some("optics geometry"),
            layout: Some(&geometry_pipeline_layout),
            vertex: wgpu::VertexState {
                module: &geometry_module,
                entry_point: Some("vs_geometry"),
                compilation_options: Default::default(),
                buffers: &[Some(wgpu::VertexBufferLayout {
                    array_stride: 24,
                    step_mode: wgpu::VertexStepMode::Vertex,
                    attributes: &wgpu::vertex_attr_array![0 => Float32x3, 1 => Float32x3],
                })],
            },
            primitive: wgpu::PrimitiveState::default(),
            depth_stencil: Some(wgpu::DepthStencilState {
                format: DEPTH,
                depth_write_enabled: Some(true),
                depth_compare: Some(wgpu::CompareFunction::Less),
                stencil: Default::default(),
                bias: Default::default(),
            }),
            multisample: Default::default(),
            fragment: Some(wgpu::FragmentState {
                module: &geometry_module,
                entry_point: Some("fs_geometry"),
                compilation_options: Default::default(),
                targets: &[target.clone(), target],
            }),
            multiview_mask: None,
            cache: None,
        });
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Validation(e.to_string()));
        }
        Ok(Self {
            layout,
            vertices,
            triangles,
            irradiance,
            frame,
            geometry_layout,
            geometry,
        })
    }

    /// Creates the targets and buffers of one stage: the caustics, and the final image of `size`
    /// when given. `surfels` are uploaded once and reused by every pass.
    pub fn prepare(
        &self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        stage: &Stage,
        surfels: &[Surfel],
        size: Option<(u32, u32)>,
    ) -> Result<PreparedOptics, crate::Error> {
        self.prepare_water(device, queue, stage, &surfels, size)
    }

    /// The targets and uniforms of a geometry map of the receiver seen in `v` (its size).
    fn geometry_target(&self, device: &wgpu::Device, label: &str, v: &View) -> GeometryTarget {
        let (w, h) = (v.width, v.height);
        let attach = wgpu::TextureUsages::RENDER_ATTACHMENT;
        let sampled = wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_SRC;
        let texture = |format, usage| texture_2d(device, label, (w, h), format, usage);
        let uniforms = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some(label),
            contents: bytemuck::bytes_of(&RawGeometry::of(v)),
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
        });
        let position = texture(FLOAT, attach | sampled);
        let normal = texture(FLOAT, attach | sampled);
        let depth = texture(DEPTH, attach);
        GeometryTarget {
            views: [&position, &normal, &depth].map(|t| t.create_view(&Default::default())),
            position,
            normal,
            bind: device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some(label),
                layout: &self.geometry_layout,
                entries: &[wgpu::BindGroupEntry {
                    binding: 0,
                    resource: uniforms.as_entire_binding(),
                }],
            }),
            uniforms,
        }
    }

    /// [`Self::prepare`] with the water drawn from `water`: splatted surfels, rays cast to the
    /// iso-surface of a caster's points, the screen-space surface (any renderer of
    /// [`crate::splat::water`]: the light's view and the camera's, each drawn on the GPU by the
    /// renderer's [`GpuWaterPass`] into the accumulation textures the optics read).
    pub fn prepare_water(
        &self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        stage: &Stage,
        water: &dyn WaterSurface,
        size: Option<(u32, u32)>,
    ) -> Result<PreparedOptics, crate::Error> {
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let limit = device.limits().max_texture_dimension_2d;
        let screen = stage.views.screen;
        let map = stage.views.map;
        let (fw, fh) = size.unwrap_or((1, 1));
        check_sizes(
            limit,
            [
                (screen.width, screen.height),
                (map.width, map.height),
                (fw, fh),
            ],
        )?;
        let camera = View::new(
            &stage.camera,
            &Light::default(),
            &stage.scene.optics.splat,
            fw,
            fh,
        )?;
        let map_geometry = self.geometry_target(device, "light geometry map", &map);
        let camera_geometry = self.geometry_target(device, "camera geometry map", &camera);
        let water = water_passes(device, queue, water, &screen, &camera)?;
        let environment = environment_texture(device, queue, stage, limit);
        // the receiver, flat normals per vertex
        let receiver = receiver_vertices(stage);
        let receiver_vertices = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("receiver"),
            contents: bytemuck::cast_slice(&receiver),
            usage: wgpu::BufferUsages::VERTEX
                | wgpu::BufferUsages::STORAGE
                | wgpu::BufferUsages::COPY_DST,
        });
        let buffer = |label, bytes: u64, extra| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: bytes.max(16),
                usage: wgpu::BufferUsages::STORAGE | extra,
                mapped_at_creation: false,
            })
        };
        let texels = u64::from(map.width) * u64::from(map.height);
        let copy = wgpu::BufferUsages::COPY_SRC | wgpu::BufferUsages::COPY_DST;
        let vertices = buffer(
            "caustics vertices",
            u64::from(screen.width) * u64::from(screen.height) * 48,
            copy,
        );
        let flux = buffer("caustics flux", texels * 16, copy);
        let irradiance = buffer("caustics irradiance", texels * 16, copy);
        let image = buffer("frame", u64::from(fw) * u64::from(fh) * 16, copy);
        let uniforms = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("optics uniforms"),
            contents: bytemuck::bytes_of(&raw_optics(stage, &camera)),
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
        });
        let (screen_colour, screen_normal) = water.light.accumulation()?;
        let (camera_colour, camera_normal) = water.camera.accumulation()?;
        let view = |t: &wgpu::Texture| t.create_view(&Default::default());
        let views = [
            view(&map_geometry.position),
            view(&map_geometry.normal),
            view(&camera_geometry.position),
            view(&camera_geometry.normal),
            view(&environment),
        ];
        fn tex(binding: u32, v: &wgpu::TextureView) -> wgpu::BindGroupEntry<'_> {
            wgpu::BindGroupEntry {
                binding,
                resource: wgpu::BindingResource::TextureView(v),
            }
        }
        fn buf(binding: u32, b: &wgpu::Buffer) -> wgpu::BindGroupEntry<'_> {
            wgpu::BindGroupEntry {
                binding,
                resource: b.as_entire_binding(),
            }
        }
        let bind = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("optics"),
            layout: &self.layout,
            entries: &[
                buf(0, &uniforms),
                tex(1, screen_colour),
                tex(2, screen_normal),
                tex(3, &views[0]),
                tex(4, &views[1]),
                buf(5, &vertices),
                buf(6, &flux),
                buf(7, &irradiance),
                tex(8, camera_colour),
                tex(9, camera_normal),
                tex(10, &views[2]),
                tex(11, &views[3]),
                buf(12, &image),
                tex(13, &views[4]),
                buf(14, &receiver_vertices),
            ],
        });
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Validation(e.to_string()).into());
        }
        Ok(PreparedOptics {
            screen,
            map,
            camera,
            frame_size: size,
            water,
            map_geometry,
            camera_geometry,
            receiver_vertices,
            receiver_count: receiver.len() as u32,
            environment_key: environment_key(stage),
            uniforms,
            flux,
            irradiance,
            image,
            bind,
        })
    }
}

struct GeometryTarget {
    position: wgpu::Texture,
    normal: wgpu::Texture,
    /// Position, normal and depth views, as the geometry pass attaches them.
    views: [wgpu::TextureView; 3],
    uniforms: wgpu::Buffer,
    bind: wgpu::BindGroup,
}

/// Refuses a screen, map or frame larger than the device's textures.
fn check_sizes(limit: u32, sizes: [(u32, u32); 3]) -> Result<(), crate::Error> {
    for (w, h) in sizes {
        if w > limit || h > limit {
            return Err(OpticsError::InvalidParameter {
                name: "resolution",
                reason: format!("{w}x{h} exceeds this device's limit of {limit}"),
            }
            .into());
        }
    }
    Ok(())
}

/// The water's passes from the light's screen and from the camera, made and prepared by the
/// water's renderer.
fn water_passes(
    device: &wgpu::Device,
    queue: &wgpu::Queue,
    water: &dyn WaterSurface,
    screen: &View,
    camera: &View,
) -> Result<Water, crate::Error> {
    let pass = |v: &View| -> Result<Box<dyn GpuWaterPass>, crate::Error> {
        let mut pass =
            water.gpu_pass(device, wgpu::TextureFormat::Rgba8Unorm, (v.width, v.height))?;
        if !water.prepare_gpu(device, queue, pass.as_mut(), v)? {
            return Err(GpuError::Validation(
                "a water pass its own renderer could not prepare".into(),
            )
            .into());
        }
        Ok(pass)
    };
    Ok(Water {
        light: pass(screen)?,
        camera: pass(camera)?,
    })
}

/// The environment image as a texture (one texel without an image, or with one larger than
/// the device's textures).
fn environment_texture(
    device: &wgpu::Device,
    queue: &wgpu::Queue,
    stage: &Stage,
    limit: u32,
) -> wgpu::Texture {
    let none = [[0.0f32; 4]];
    let (ew, eh, env_pixels): (u32, u32, &[[f32; 4]]) = match &stage.scene.environment.pixels {
        Some((w, h, p)) if *w <= limit && *h <= limit => (*w, *h, p.as_slice()),
        _ => (1, 1, &none),
    };
    device.create_texture_with_data(
        queue,
        &texture_descriptor(
            "environment",
            (ew, eh),
            FLOAT,
            wgpu::TextureUsages::TEXTURE_BINDING,
        ),
        wgpu::util::TextureDataOrder::LayerMajor,
        bytemuck::cast_slice(env_pixels),
    )
}

/// The water's passes: the light's and the camera's.
struct Water {
    light: Box<dyn GpuWaterPass>,
    camera: Box<dyn GpuWaterPass>,
}

/// The GPU resources of one stage, ready to record.
pub struct PreparedOptics {
    screen: View,
    map: View,
    camera: View,
    frame_size: Option<(u32, u32)>,
    water: Water,
    map_geometry: GeometryTarget,
    camera_geometry: GeometryTarget,
    receiver_vertices: wgpu::Buffer,
    receiver_count: u32,
    /// What the environment texture was made from.
    environment_key: (u32, u32, Option<std::path::PathBuf>),
    uniforms: wgpu::Buffer,
    flux: wgpu::Buffer,
    irradiance: wgpu::Buffer,
    image: wgpu::Buffer,
    bind: wgpu::BindGroup,
}

/// What [`PreparedOptics::read`] copies back.
#[derive(Clone, Debug, PartialEq)]
pub struct GpuOpticsResult {
    /// Caustics map flux per texel (as [`crate::optics::Caustics::flux`]).
    pub flux: Vec<[f32; 4]>,
    /// Caustics map irradiance per texel (as [`crate::optics::Caustics::irradiance`]).
    pub irradiance: Vec<[f32; 4]>,
    /// The final image when one was prepared: display image and linear radiance.
    pub frame: Option<(RgbaImage, Vec<[f32; 4]>)>,
}

/// Wall-clock milliseconds of the two halves (each submitted and waited for on its own).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct OpticsTimes {
    pub caustics_ms: f64,
    pub frame_ms: f64,
}

fn groups(n: u32) -> u32 {
    n.div_ceil(8)
}

/// The environment image's size and path (`(1, 1, None)` without one).
fn environment_key(stage: &Stage) -> (u32, u32, Option<std::path::PathBuf>) {
    match &stage.scene.environment.pixels {
        Some((w, h, _)) => (*w, *h, stage.scene.environment.image.clone()),
        None => (1, 1, None),
    }
}

/// The receiver's vertices with flat normals, as the geometry pass reads them.
fn receiver_vertices(stage: &Stage) -> Vec<[f32; 6]> {
    stage
        .receiver
        .triangles
        .iter()
        .flat_map(|t| {
            let n = (t[1] - t[0]).cross(t[2] - t[0]).normalize_or_zero();
            t.map(|p| [p.x, p.y, p.z, n.x, n.y, n.z])
        })
        .collect()
}

impl PreparedOptics {
    /// Starts what the water's passes read back without a wait (the screen-space renderer's
    /// tiles' statistics) once the encoder they recorded into is submitted.
    pub fn after_submit(&mut self) {
        self.water.light.after_submit();
        self.water.camera.after_submit();
    }

    /// Makes this frame's stage and surfels current without creating anything, when its
    /// targets fit: the same screen, map and image sizes, receiver triangle count and
    /// environment image. Uniforms, receiver vertices and surfels are written through the queue
    /// (the surfel buffer grows geometrically when a frame has more). Returns `false`, changing
    /// nothing, when the stage needs new targets ([`OpticsGpu::prepare`] then).
    pub fn update(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        stage: &Stage,
        surfels: &[Surfel],
    ) -> Result<bool, crate::Error> {
        self.update_water(device, queue, stage, &surfels)
    }

    /// Buffers and bind groups the water's passes made in the last [`Self::update_water`] (0 in
    /// the steady state of a sequence: every renderer writes its inputs into kept buffers).
    #[must_use]
    pub fn water_created(&self) -> usize {
        self.water.light.created() + self.water.camera.created()
    }

    /// [`Self::update`] with the water drawn from `water`; `false` too when it is drawn another
    /// way than the prepared stage's.
    pub fn update_water(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        stage: &Stage,
        water: &dyn WaterSurface,
    ) -> Result<bool, crate::Error> {
        let (screen, map) = (stage.views.screen, stage.views.map);
        let Some((fw, fh)) = self.frame_size else {
            return Ok(false);
        };
        let receiver = receiver_vertices(stage);
        if (screen.width, screen.height) != (self.screen.width, self.screen.height)
            || (map.width, map.height) != (self.map.width, self.map.height)
            || receiver.len() as u32 != self.receiver_count
            || environment_key(stage) != self.environment_key
        {
            return Ok(false);
        }
        let camera = View::new(
            &stage.camera,
            &Light::default(),
            &stage.scene.optics.splat,
            fw,
            fh,
        )?;
        // the same sizes (checked above), so the targets the bind groups hold stay; drawn
        // another way than prepared: new targets
        if !water.prepare_gpu(device, queue, self.water.light.as_mut(), &screen)?
            || !water.prepare_gpu(device, queue, self.water.camera.as_mut(), &camera)?
        {
            return Ok(false);
        }
        queue.write_buffer(
            &self.uniforms,
            0,
            bytemuck::bytes_of(&raw_optics(stage, &camera)),
        );
        queue.write_buffer(
            &self.map_geometry.uniforms,
            0,
            bytemuck::bytes_of(&RawGeometry::of(&map)),
        );
        queue.write_buffer(
            &self.camera_geometry.uniforms,
            0,
            bytemuck::bytes_of(&RawGeometry::of(&camera)),
        );
        queue.write_buffer(&self.receiver_vertices, 0, bytemuck::cast_slice(&receiver));
        self.screen = screen;
        self.map = map;
        self.camera = camera;
        Ok(true)
    }

    fn draw_geometry(
        &self,
        optics: &OpticsGpu,
        encoder: &mut wgpu::CommandEncoder,
        target: &GeometryTarget,
    ) {
        let [position, normal, depth] = &target.views;
        let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("optics geometry"),
            color_attachments: &[crate::gpu::cleared(position), crate::gpu::cleared(normal)],
            depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                view: depth,
                depth_ops: Some(wgpu::Operations {
                    load: wgpu::LoadOp::Clear(1.0),
                    store: wgpu::StoreOp::Store,
                }),
                stencil_ops: None,
            }),
            ..Default::default()
        });
        pass.set_pipeline(&optics.geometry);
        pass.set_bind_group(0, &target.bind, &[]);
        pass.set_vertex_buffer(0, self.receiver_vertices.slice(..));
        pass.draw(0..self.receiver_count, 0..1);
    }

    fn dispatch(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        pipeline: &wgpu::ComputePipeline,
        (w, h): (u32, u32),
    ) {
        let mut pass = encoder.begin_compute_pass(&Default::default());
        pass.set_pipeline(pipeline);
        pass.set_bind_group(0, &self.bind, &[]);
        pass.dispatch_workgroups(groups(w), groups(h), 1);
    }

    /// Records the caustics (§5.1): the light's splatting of the water, the light's geometry map,
    /// the caustics vertices, the caustics triangles into the (cleared) map, its irradiance.
    pub fn encode_caustics(
        &self,
        queue: &wgpu::Queue,
        optics: &OpticsGpu,
        encoder: &mut wgpu::CommandEncoder,
    ) -> Result<(), crate::Error> {
        self.water.light.encode(queue, encoder)?;
        self.draw_geometry(optics, encoder, &self.map_geometry);
        encoder.clear_buffer(&self.flux, 0, None);
        let screen = (self.screen.width, self.screen.height);
        let map = (self.map.width, self.map.height);
        self.dispatch(encoder, &optics.vertices, screen);
        self.dispatch(encoder, &optics.triangles, screen);
        self.dispatch(encoder, &optics.irradiance, map);
        Ok(())
    }

    /// Records the final image (§5.2), after [`Self::encode_caustics`]: the camera's splatting,
    /// the camera's geometry map, the per-pixel optics. A no-op when no image was prepared.
    pub fn encode_frame(
        &self,
        queue: &wgpu::Queue,
        optics: &OpticsGpu,
        encoder: &mut wgpu::CommandEncoder,
    ) -> Result<(), crate::Error> {
        let Some(size) = self.frame_size else {
            return Ok(());
        };
        self.water.camera.encode(queue, encoder)?;
        self.draw_geometry(optics, encoder, &self.camera_geometry);
        self.dispatch(encoder, &optics.frame, size);
        Ok(())
    }

    /// The final image's storage buffer (linear RGBA `vec4<f32>` per pixel, row-major from the
    /// top), for a pass that presents it; `None` when no image was prepared.
    #[must_use]
    pub fn image_buffer(&self) -> Option<(&wgpu::Buffer, (u32, u32))> {
        self.frame_size.map(|size| (&self.image, size))
    }

    /// Copies the caustics map and the image back.
    pub fn read(&self, ctx: &GpuContext) -> Result<GpuOpticsResult, GpuError> {
        let flux: Vec<[f32; 4]> = gpu::read_buffer(ctx, &self.flux)?;
        let irradiance: Vec<[f32; 4]> = gpu::read_buffer(ctx, &self.irradiance)?;
        let texels = (self.map.width * self.map.height) as usize;
        let frame = match self.frame_size {
            Some((w, h)) => {
                let linear: Vec<[f32; 4]> = gpu::read_buffer(ctx, &self.image)?;
                let linear = linear[..(w * h) as usize].to_vec();
                let image = RgbaImage::from_fn(w, h, |x, y| {
                    let [r, g, b] = encode(Vec4::from(linear[(y * w + x) as usize]).truncate());
                    image::Rgba([r, g, b, 255])
                });
                Some((image, linear))
            }
            None => None,
        };
        Ok(GpuOpticsResult {
            flux: flux[..texels].to_vec(),
            irradiance: irradiance[..texels].to_vec(),
            frame,
        })
    }
}

/// Caustics and (when `size` is given) the final image, headless: prepared, recorded, submitted,
/// read back; with the wall-clock time of each half.
pub fn render_gpu(
    ctx: &GpuContext,
    stage: &Stage,
    surfels: &[Surfel],
    size: Option<(u32, u32)>,
) -> Result<(GpuOpticsResult, OpticsTimes), crate::Error> {
    let optics = OpticsGpu::new(&ctx.device)?;
    let prepared = optics.prepare(&ctx.device, &ctx.queue, stage, surfels, size)?;
    let times = run_timed(ctx, &optics, &prepared)?;
    Ok((prepared.read(ctx)?, times))
}

/// Records, submits and waits for the caustics and then the frame, timing each.
pub fn run_timed(
    ctx: &GpuContext,
    optics: &OpticsGpu,
    prepared: &PreparedOptics,
) -> Result<OpticsTimes, crate::Error> {
    let device = &ctx.device;
    let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
    let run = |frame: bool| -> Result<f64, crate::Error> {
        let mut encoder = device.create_command_encoder(&Default::default());
        if frame {
            prepared.encode_frame(&ctx.queue, optics, &mut encoder)?;
        } else {
            prepared.encode_caustics(&ctx.queue, optics, &mut encoder)?;
        }
        let start = Instant::now();
        ctx.queue.submit([encoder.finish()]);
        crate::gpu::wait(device)?;
        Ok(start.elapsed().as_secs_f64() * 1e3)
    };
    let times = OpticsTimes {
        caustics_ms: run(false)?,
        frame_ms: run(true)?,
    };
    if let Some(e) = pollster::block_on(scope.pop()) {
        return Err(GpuError::Validation(e.to_string()).into());
    }
    Ok(times)
}
