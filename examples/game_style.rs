//! How a game uses the splatting renderer: on its own `wgpu::Device`, recording into its own
//! command encoder and drawing into its own texture. The crate creates no device and submits
//! nothing; the game owns the frame.
//!
//! Run: `cargo run --release --example game_style [OUT.png]` (writes `game_style.png` by
//! default; needs a GPU or Mesa's lavapipe).

use fluid_surfels::gpu::REQUIRED_FEATURES;
use fluid_surfels::splat::gpu::SplatRenderer;
use fluid_surfels::splat::{self, Camera, Light, SplatParams, View};
use fluid_surfels::{density, scenes, surfels};
use glam::Vec3;

const WIDTH: u32 = 640;
const HEIGHT: u32 = 480;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    // --- the game's own device (here headless; a game would also have a surface) ---
    let instance =
        wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle().with_env());
    let adapter = match pollster::block_on(instance.request_adapter(&Default::default())) {
        Ok(a) => a,
        Err(e) => {
            eprintln!("no GPU adapter ({e}); install a Vulkan driver such as mesa-vulkan-drivers");
            return Ok(());
        }
    };
    let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
        label: Some("game"),
        // the splatting passes blend into 32-bit float targets
        required_features: REQUIRED_FEATURES,
        ..Default::default()
    }))?;
    let target = device.create_texture(&wgpu::TextureDescriptor {
        label: Some("game frame"),
        size: wgpu::Extent3d {
            width: WIDTH,
            height: HEIGHT,
            depth_or_array_layers: 1,
        },
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format: wgpu::TextureFormat::Rgba8UnormSrgb,
        usage: wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
        view_formats: &[],
    });
    let target_view = target.create_view(&Default::default());

    // --- water surfels from the particles of the simulation (here a built-in scene) ---
    let scene = scenes::build(scenes::SceneName::Column, Some(14))?;
    let p = &scene.particles.positions;
    let h = scene.support_radius;
    let spec = density::GridSpec::around(p, h, density::Resolution::LongestAxis(96))?;
    let grid = density::density_grid(p, &spec, density::Kernel::Wyvill, h, 1 << 30)?;
    let s = surfels::extract(&grid, p, density::Kernel::Wyvill, h, &Default::default())?;
    let water = splat::surfels_from(&s.positions, &s.normals, &s.radii, splat::WATER);

    // --- once: the renderer for the game's target format and size, and the surfel upload ---
    let renderer = SplatRenderer::new(&device, target.format(), WIDTH, HEIGHT)?;
    let uploaded = SplatRenderer::upload(&device, &water);

    // --- every frame: the camera moves, the passes go into the game's encoder ---
    let (lo, hi) = splat::bounds(&water).unwrap_or((Vec3::ZERO, Vec3::ONE));
    let camera = Camera::framing(lo, hi);
    let view = View::new(
        &camera,
        &Light::default(),
        &SplatParams::default(),
        WIDTH,
        HEIGHT,
    )?;
    let mut encoder = device.create_command_encoder(&Default::default());
    // ... the game's own passes would be recorded here ...
    renderer.encode(&device, &mut encoder, &target_view, &uploaded, &view)?;
    // ... and its UI after ...
    let row = (WIDTH * 4).div_ceil(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT)
        * wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
    let readback = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("screenshot"),
        size: u64::from(row * HEIGHT),
        usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
        mapped_at_creation: false,
    });
    encoder.copy_texture_to_buffer(
        target.as_image_copy(),
        wgpu::TexelCopyBufferInfo {
            buffer: &readback,
            layout: wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(row),
                rows_per_image: Some(HEIGHT),
            },
        },
        target.size(),
    );
    queue.submit([encoder.finish()]);

    // --- a screenshot, to see what the game would show ---
    readback.slice(..).map_async(wgpu::MapMode::Read, |_| {});
    device.poll(wgpu::PollType::wait_indefinitely())?;
    let data = readback.slice(..).get_mapped_range()?;
    let mut pixels = Vec::with_capacity((WIDTH * HEIGHT * 4) as usize);
    for y in 0..HEIGHT as usize {
        pixels.extend_from_slice(&data[y * row as usize..][..(WIDTH * 4) as usize]);
    }
    let image = image::RgbaImage::from_raw(WIDTH, HEIGHT, pixels).ok_or("screenshot size")?;
    let out = std::env::args()
        .nth(1)
        .unwrap_or_else(|| "game_style.png".into());
    image.save(&out)?;
    println!(
        "{} surfels splatted into the game's {WIDTH}x{HEIGHT} {:?} target; wrote {out}",
        uploaded.len,
        target.format()
    );
    Ok(())
}
