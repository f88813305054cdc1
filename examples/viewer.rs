//! A viewer: plays a particle sequence (files with a frame pattern, or the built-in `column`
//! simulation) through `GpuPipeline` in a window, with an orbit camera. Each played frame runs
//! `GpuPipeline::prepare` once (with the EWA renderer and the chain or particle source the
//! density grid and the surfels are made on the GPU and stay there); a paused frame is redrawn
//! from its surfels where they are as the camera moves.
//!
//! ```text
//! cargo run --release --example viewer                          # the column scene
//! cargo run --release --example viewer -- --input 'sim/frame_{}.vtk'
//! cargo run --release --example viewer -- --headless --frames 10 --out out/viewer
//! cargo run --release --example viewer -- --renderer particle-splat   # Adams et al. 2006
//! cargo run --release --example viewer -- --renderer ray-cast         # Xiao et al. (slow on lavapipe)
//! cargo run --release --example viewer -- --renderer ssfr             # Oliveira and Paiva, screen space
//! cargo run --release --example viewer -- --narrow-band               # the density grid sparse
//! ```
//!
//! Keys: Space pause/play, Right (or N) one frame on, S next surfel source (chain, particles,
//! refined), P next renderer (EWA surfels, particle splatting, ray casting, screen space), R finished frame / shaded
//! splats, Escape quit. Drag with the left mouse button to
//! orbit, scroll to zoom. With `--headless --frames N --out DIR` there is no window: the first N
//! frames are written as PNGs (finished frames, or shaded splats with `--splats`), so tests can run
//! it without a display. Needs a GPU or Mesa's lavapipe.

use std::path::PathBuf;
use std::sync::Arc;

use fluid_surfels::gpu::{GpuContext, REQUIRED_FEATURES};
use fluid_surfels::pipeline::{Frame, GpuPipeline, PipelineParams, Renderer, SurfelSource};
use fluid_surfels::scenes::{ColumnParams, ColumnSim, column_pool};
use fluid_surfels::sequence::FramePattern;
use fluid_surfels::splat::Camera;
use fluid_surfels::{ParticleSet, io};
use glam::Vec3;
use winit::application::ApplicationHandler;
use winit::event::{ElementState, MouseButton, MouseScrollDelta, WindowEvent};
use winit::event_loop::{ActiveEventLoop, ControlFlow, EventLoop};
use winit::keyboard::{Key, NamedKey};
use winit::window::{Window, WindowId};

type Result<T> = std::result::Result<T, Box<dyn std::error::Error>>;

struct Args {
    input: Option<String>,
    headless: bool,
    frames: usize,
    out: PathBuf,
    splats: bool,
    size: (u32, u32),
    renderer: Renderer,
    narrow_band: bool,
}

fn args() -> std::result::Result<Args, String> {
    let mut a = Args {
        input: None,
        headless: false,
        frames: 10,
        out: PathBuf::from("out/viewer"),
        splats: false,
        size: (640, 480),
        renderer: Renderer::Ewa,
        narrow_band: false,
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        let mut value = || it.next().ok_or(format!("{flag} needs a value"));
        match flag.as_str() {
            "--input" => a.input = Some(value()?),
            "--headless" => a.headless = true,
            "--frames" => a.frames = value()?.parse().map_err(|e| format!("--frames: {e}"))?,
            "--out" => a.out = PathBuf::from(value()?),
            "--splats" => a.splats = true,
            "--narrow-band" => a.narrow_band = true,
            "--renderer" => {
                let v = value()?;
                a.renderer = RENDERERS
                    .into_iter()
                    .find(|r| r.as_str() == v)
                    .ok_or(format!(
                        "--renderer {v}: expected ewa, particle-splat, ray-cast or ssfr"
                    ))?;
            }
            "--size" => {
                let v = value()?;
                let (w, h) = v
                    .split_once('x')
                    .ok_or(format!("--size {v}: expected WxH"))?;
                a.size = (
                    w.parse().map_err(|e| format!("--size: {e}"))?,
                    h.parse().map_err(|e| format!("--size: {e}"))?,
                );
            }
            other => return Err(format!("unknown argument {other}")),
        }
    }
    Ok(a)
}

/// Where the frames come from; plays in a loop.
enum Source {
    Column(Box<ColumnSim>),
    Files {
        pattern: FramePattern,
        frames: Vec<usize>,
        at: usize,
    },
}

impl Source {
    fn new(input: Option<&str>) -> Result<Self> {
        Ok(match input {
            None => Self::Column(Box::new(ColumnSim::new(ColumnParams::default())?)),
            Some(text) => {
                let pattern = FramePattern::parse(text)?
                    .ok_or_else(|| format!("`{text}` needs a {{}} for the frame number"))?;
                let frames = pattern.existing_frames()?;
                if frames.is_empty() {
                    return Err(format!("no file matches `{text}`").into());
                }
                Self::Files {
                    pattern,
                    frames,
                    at: 0,
                }
            }
        })
    }

    /// The pipeline's settings for this source, the density grid sparse with `narrow_band`.
    fn params(&self, narrow_band: bool) -> PipelineParams {
        let mut params = match self {
            Self::Column(sim) => PipelineParams {
                support_radius: Some(sim.support_radius()),
                scene: column_pool(ColumnParams::default().tank),
                ..Default::default()
            },
            Self::Files { .. } => PipelineParams::default(),
        };
        params.grid.narrow_band = narrow_band;
        params
    }

    fn particles(&self) -> Result<ParticleSet> {
        Ok(match self {
            Self::Column(sim) => sim.particles().clone(),
            Self::Files {
                pattern,
                frames,
                at,
            } => io::read_particles(&pattern.path(frames[*at]), None)?,
        })
    }

    fn step(&mut self) {
        match self {
            Self::Column(sim) => {
                if sim.frame() >= 240 {
                    **sim = ColumnSim::new(ColumnParams::default()).expect("the default column");
                } else {
                    sim.step_frame();
                }
            }
            Self::Files { frames, at, .. } => *at = (*at + 1) % frames.len(),
        }
    }
}

/// An orbit around a target: yaw and pitch in radians, distance.
#[derive(Clone, Copy)]
struct Orbit {
    target: Vec3,
    yaw: f32,
    pitch: f32,
    distance: f32,
    base: Camera,
}

impl Orbit {
    fn from(camera: Camera) -> Self {
        let d = camera.eye - camera.target;
        Self {
            target: camera.target,
            yaw: d.x.atan2(d.z),
            pitch: (d.y / d.length().max(1e-6)).asin(),
            distance: d.length(),
            base: camera,
        }
    }

    fn camera(&self) -> Camera {
        let dir = Vec3::new(
            self.pitch.cos() * self.yaw.sin(),
            self.pitch.sin(),
            self.pitch.cos() * self.yaw.cos(),
        );
        Camera {
            eye: self.target + dir * self.distance,
            target: self.target,
            near: (self.distance * 0.02).max(1e-4),
            far: self.distance * 20.0 + 1.0,
            ..self.base
        }
    }
}

const SOURCES: [SurfelSource; 3] = SurfelSource::ALL;

/// The renderers, in the order P steps through them.
const RENDERERS: [Renderer; 4] = [
    Renderer::Ewa,
    Renderer::ParticleSplat,
    Renderer::RayCast,
    Renderer::Ssfr,
];

/// The device, the pipeline and what the window shows.
struct Viewer {
    device: wgpu::Device,
    queue: wgpu::Queue,
    gpu: GpuPipeline,
    source: Source,
    /// The particles of the current played frame, and whether the pipeline has run on them yet.
    particles: Option<(ParticleSet, bool)>,
    /// The last frame the pipeline made (its surfels on the GPU, or the CPU's).
    frame: Option<Frame>,
    orbit: Option<Orbit>,
    show_splats: bool,
    source_index: usize,
}

impl Viewer {
    fn new(
        device: wgpu::Device,
        queue: wgpu::Queue,
        format: wgpu::TextureFormat,
        size: (u32, u32),
        source: Source,
        (show_splats, narrow_band): (bool, bool),
    ) -> Result<Self> {
        let params = source.params(narrow_band);
        let gpu = GpuPipeline::new(&device, &queue, format, size, &params)?;
        Ok(Self {
            device,
            queue,
            gpu,
            source,
            particles: None,
            frame: None,
            orbit: None,
            show_splats,
            source_index: 0,
        })
    }

    /// Takes the current particles (once per played frame); the next `draw` runs the pipeline
    /// on them.
    fn update(&mut self) -> Result<()> {
        self.particles = Some((self.source.particles()?, false));
        Ok(())
    }

    fn camera(&mut self) -> Camera {
        let fitted = self.gpu.cpu().camera();
        let orbit = match (self.orbit, fitted) {
            (Some(o), _) => o,
            (None, Some(c)) => Orbit::from(c),
            (None, None) => {
                let (lo, hi) = self
                    .frame
                    .as_ref()
                    .and_then(fluid_surfels::pipeline::Frame::water_box)
                    .unwrap_or((Vec3::ZERO, Vec3::ONE));
                Orbit::from(
                    self.gpu
                        .cpu()
                        .params()
                        .scene
                        .camera
                        .unwrap_or(Camera::framing(lo, hi)),
                )
            }
        };
        self.orbit = Some(orbit);
        orbit.camera()
    }

    /// Records the current frame into `encoder`, drawn into `target`: on new particles the
    /// whole pipeline (`GpuPipeline::prepare`: the density grid and the surfels on the GPU where
    /// the renderer and source have them), else the last frame from the current camera. Call
    /// `GpuPipeline::after_submit` once the encoder is submitted.
    fn draw(
        &mut self,
        encoder: &mut wgpu::CommandEncoder,
        target: &wgpu::TextureView,
    ) -> Result<()> {
        // before the first frame the pipeline fits its own camera
        if self.frame.is_some() {
            let camera = self.camera();
            self.gpu.cpu_mut().set_camera(camera);
        }
        if let Some((particles, done)) = self.particles.as_mut()
            && !*done
        {
            *done = true;
            let frame = self
                .gpu
                .prepare(&self.device, &self.queue, encoder, &*particles)?;
            self.frame = Some(frame);
            if !self.show_splats {
                self.gpu.draw_into(encoder, target);
                return Ok(());
            }
        }
        let Some(frame) = self.frame.as_ref() else {
            return Ok(());
        };
        if self.show_splats {
            self.gpu
                .encode_splats(&self.device, &self.queue, encoder, frame, target)?;
            return Ok(());
        }
        self.gpu
            .prepare_frame(&self.device, &self.queue, encoder, frame)?;
        self.gpu.draw_into(encoder, target);
        Ok(())
    }

    fn resize(&mut self, w: u32, h: u32) -> Result<()> {
        self.gpu.resize(&self.device, w, h)?;
        Ok(())
    }

    fn next_renderer(&mut self) -> Result<()> {
        let now = self.gpu.cpu().params().renderer;
        let k = RENDERERS.iter().position(|&r| r == now).unwrap_or(0);
        let next = RENDERERS[(k + 1) % RENDERERS.len()];
        self.gpu.cpu_mut().set_renderer(next);
        self.update()
    }

    fn next_source(&mut self) -> Result<()> {
        self.source_index = (self.source_index + 1) % SOURCES.len();
        self.gpu.cpu_mut().set_source(SOURCES[self.source_index]);
        self.update()
    }
}

/// `--headless`: the first frames as PNGs, no window.
fn headless(args: &Args) -> Result<()> {
    let ctx = match GpuContext::headless() {
        Ok(c) => c,
        Err(e) => {
            eprintln!("no GPU adapter ({e}); install a Vulkan driver such as mesa-vulkan-drivers");
            return Ok(());
        }
    };
    std::fs::create_dir_all(&args.out)?;
    let format = wgpu::TextureFormat::Rgba8UnormSrgb;
    let source = Source::new(args.input.as_deref())?;
    let mut viewer = Viewer::new(
        ctx.device.clone(),
        ctx.queue.clone(),
        format,
        args.size,
        source,
        (args.splats, args.narrow_band),
    )?;
    viewer.gpu.cpu_mut().set_renderer(args.renderer);
    for f in 0..args.frames {
        viewer.update()?;
        let texture = fluid_surfels::gpu::texture_2d(
            &ctx.device,
            "viewer frame",
            args.size,
            format,
            wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
        );
        let view = texture.create_view(&Default::default());
        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        viewer.draw(&mut encoder, &view)?;
        ctx.queue.submit([encoder.finish()]);
        viewer.gpu.after_submit();
        let path = args.out.join(format!("frame_{f:04}.png"));
        fluid_surfels::gpu::read_rgba8(&ctx, &texture)?.save(&path)?;
        println!(
            "wrote {} ({} surfels, {})",
            path.display(),
            viewer.frame.as_ref().map_or(0, |f| if f.surfels_on_gpu {
                f.detail.surfels
            } else {
                f.render_surfels.len()
            }),
            if args.splats {
                "shaded splats"
            } else {
                "finished frame"
            }
        );
        viewer.source.step();
    }
    Ok(())
}

/// The window, its surface and the viewer.
struct Windowed {
    args: Args,
    state: Option<(
        Arc<Window>,
        wgpu::Surface<'static>,
        wgpu::SurfaceConfiguration,
        Viewer,
    )>,
    paused: bool,
    step: bool,
    drag: Option<(f64, f64)>,
    error: Option<Box<dyn std::error::Error>>,
}

impl Windowed {
    fn open(&mut self, event_loop: &ActiveEventLoop) -> Result<()> {
        let window = Arc::new(
            event_loop.create_window(
                Window::default_attributes()
                    .with_title("fluid-surfels viewer")
                    .with_inner_size(winit::dpi::PhysicalSize::new(
                        self.args.size.0,
                        self.args.size.1,
                    )),
            )?,
        );
        let instance =
            wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle().with_env());
        let surface = instance.create_surface(window.clone())?;
        let adapter = pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
            compatible_surface: Some(&surface),
            ..Default::default()
        }))?;
        let (device, queue) =
            pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
                label: Some("viewer"),
                required_features: REQUIRED_FEATURES,
                ..Default::default()
            }))?;
        let size = window.inner_size();
        let (w, h) = (size.width.max(1), size.height.max(1));
        let caps = surface.get_capabilities(&adapter);
        let format = caps
            .formats
            .iter()
            .copied()
            .find(|f| {
                matches!(
                    f,
                    wgpu::TextureFormat::Rgba8UnormSrgb | wgpu::TextureFormat::Bgra8UnormSrgb
                )
            })
            .unwrap_or(caps.formats[0]);
        let config = wgpu::SurfaceConfiguration {
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT,
            format,
            width: w,
            height: h,
            present_mode: wgpu::PresentMode::AutoVsync,
            desired_maximum_frame_latency: 2,
            alpha_mode: caps.alpha_modes[0],
            view_formats: vec![],
            color_space: wgpu::SurfaceColorSpace::Auto,
        };
        surface.configure(&device, &config);
        let source = Source::new(self.args.input.as_deref())?;
        let mut viewer = Viewer::new(
            device,
            queue,
            format,
            (w, h),
            source,
            (self.args.splats, self.args.narrow_band),
        )?;
        viewer.gpu.cpu_mut().set_renderer(self.args.renderer);
        viewer.update()?;
        self.state = Some((window, surface, config, viewer));
        Ok(())
    }

    fn redraw(&mut self) -> Result<()> {
        let Some((window, surface, _, viewer)) = self.state.as_mut() else {
            return Ok(());
        };
        if !self.paused || self.step {
            viewer.source.step();
            viewer.update()?;
            self.step = false;
        }
        let texture = match surface.get_current_texture() {
            wgpu::CurrentSurfaceTexture::Success(t)
            | wgpu::CurrentSurfaceTexture::Suboptimal(t) => t,
            _ => return Ok(()),
        };
        let view = texture.texture.create_view(&Default::default());
        let mut encoder = viewer.device.create_command_encoder(&Default::default());
        viewer.draw(&mut encoder, &view)?;
        viewer.queue.submit([encoder.finish()]);
        viewer.gpu.after_submit();
        window.pre_present_notify();
        viewer.queue.present(texture);
        Ok(())
    }
}

impl ApplicationHandler for Windowed {
    fn resumed(&mut self, event_loop: &ActiveEventLoop) {
        if self.state.is_none()
            && let Err(e) = self.open(event_loop)
        {
            self.error = Some(e);
            event_loop.exit();
        }
    }

    fn window_event(&mut self, event_loop: &ActiveEventLoop, _: WindowId, event: WindowEvent) {
        let result = match event {
            WindowEvent::CloseRequested => {
                event_loop.exit();
                Ok(())
            }
            WindowEvent::Resized(size) => match self.state.as_mut() {
                Some((_, surface, config, viewer)) if size.width > 0 && size.height > 0 => {
                    config.width = size.width;
                    config.height = size.height;
                    surface.configure(&viewer.device, config);
                    viewer.resize(size.width, size.height)
                }
                _ => Ok(()),
            },
            WindowEvent::KeyboardInput { event, .. } if event.state == ElementState::Pressed => {
                match (&event.logical_key, self.state.as_mut()) {
                    (Key::Named(NamedKey::Escape), _) => {
                        event_loop.exit();
                        Ok(())
                    }
                    (Key::Named(NamedKey::Space), _) => {
                        self.paused = !self.paused;
                        Ok(())
                    }
                    (Key::Named(NamedKey::ArrowRight), _) => {
                        self.step = true;
                        Ok(())
                    }
                    (Key::Character(c), Some((.., viewer))) => match c.as_str() {
                        "n" | "N" => {
                            self.step = true;
                            Ok(())
                        }
                        "s" | "S" => viewer.next_source(),
                        "p" | "P" => viewer.next_renderer(),
                        "r" | "R" => {
                            viewer.show_splats = !viewer.show_splats;
                            Ok(())
                        }
                        _ => Ok(()),
                    },
                    _ => Ok(()),
                }
            }
            WindowEvent::MouseInput {
                state,
                button: MouseButton::Left,
                ..
            } => {
                if state == ElementState::Released {
                    self.drag = None;
                } else {
                    self.drag = Some((f64::NAN, f64::NAN));
                }
                Ok(())
            }
            WindowEvent::CursorMoved { position, .. } => {
                if let (Some((x, y)), Some((.., viewer))) = (self.drag, self.state.as_mut()) {
                    if let Some(o) = viewer.orbit.as_mut()
                        && x.is_finite()
                    {
                        o.yaw -= ((position.x - x) * 0.01) as f32;
                        o.pitch = (o.pitch + ((position.y - y) * 0.01) as f32).clamp(-1.5, 1.5);
                    }
                    self.drag = Some((position.x, position.y));
                }
                Ok(())
            }
            WindowEvent::MouseWheel { delta, .. } => {
                if let Some(o) = self.state.as_mut().and_then(|(.., v)| v.orbit.as_mut()) {
                    let lines = match delta {
                        MouseScrollDelta::LineDelta(_, y) => y,
                        MouseScrollDelta::PixelDelta(p) => (p.y / 40.0) as f32,
                    };
                    o.distance *= 0.9f32.powf(lines);
                }
                Ok(())
            }
            WindowEvent::RedrawRequested => self.redraw(),
            _ => Ok(()),
        };
        if let Err(e) = result {
            self.error = Some(e);
            event_loop.exit();
        }
    }

    fn about_to_wait(&mut self, _: &ActiveEventLoop) {
        if let Some((window, ..)) = &self.state {
            window.request_redraw();
        }
    }
}

fn main() -> Result<()> {
    let args = args()?;
    if args.headless {
        return headless(&args);
    }
    let event_loop = EventLoop::new()?;
    event_loop.set_control_flow(ControlFlow::Poll);
    let mut app = Windowed {
        args,
        state: None,
        paused: false,
        step: false,
        drag: None,
        error: None,
    };
    event_loop.run_app(&mut app)?;
    match app.error {
        Some(e) => Err(e),
        None => Ok(()),
    }
}
