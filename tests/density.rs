//! The CPU density grid: streaming, the naive reference, and absurd input.

use fluid_surfels::density::{self, DensityError, GridSpec, Kernel, Resolution};
use fluid_surfels::scenes;
use glam::Vec3;

fn water() -> (Vec<Vec3>, f32) {
    // a jittered block, h twice the spacing (the paper's setting in the benchmark)
    let scene = scenes::block(&scenes::BlockParams {
        counts: [14, 9, 11],
        ..Default::default()
    })
    .unwrap();
    (scene.particles.positions, 2.0 * scene.spacing)
}

#[test]
fn streaming_equals_whole_grid_and_the_naive_reference() {
    let (p, h) = water();
    for kernel in [Kernel::Wyvill, Kernel::CubicSpline] {
        let spec = GridSpec::around(&p, h, Resolution::LongestAxis(48)).unwrap();
        let whole = density::density_grid(&p, &spec, kernel, h, 1 << 30).unwrap();
        for slab in [1, 3, 4, 7, 64] {
            let mut streamed = Vec::new();
            let mut next = 0;
            density::splat_slabs(&p, &spec, kernel, h, slab, |k0, values| {
                assert_eq!(k0, next, "slabs arrive in z order");
                next += slab.min(spec.dims[2] - k0);
                streamed.extend(values);
            })
            .unwrap();
            assert_eq!(streamed, whole.values, "{kernel:?}, slabs of {slab} planes");
        }
        // a buffer of earlier frames, longer or shorter and holding old values, gives the same
        let cells = whole.values.len();
        for old in [
            vec![7.0f32; cells + 100],
            vec![-3.0f32; cells / 2],
            vec![1.0f32; cells],
        ] {
            let points = density::Points::uniform(&p, h);
            let reused = density::points_grid_in(points, &spec, kernel, 1 << 30, old).unwrap();
            assert_eq!(reused.values, whole.values, "{kernel:?}, a reused buffer");
        }
        let naive = density::density_naive(&p, &spec, kernel, h).unwrap();
        let max = naive.max();
        let (worst, at) = naive
            .values
            .iter()
            .zip(&whole.values)
            .enumerate()
            .map(|(i, (a, b))| ((a - b).abs(), i))
            .fold((0.0f32, 0), |acc, x| if x.0 > acc.0 { x } else { acc });
        println!(
            "{kernel:?}: {:?} grid, max density {max}, largest difference from the naive reference {worst:e} at {at}",
            spec.dims
        );
        assert!(
            worst <= 1e-5 * max,
            "{kernel:?}: {worst} at grid point {at}"
        );
        // mass is conserved: the grid sums to the particle count over the cell volume
        let total: f64 =
            whole.values.iter().map(|&v| v as f64).sum::<f64>() * (spec.spacing as f64).powi(3);
        assert!(
            (total / p.len() as f64 - 1.0).abs() < 0.02,
            "{kernel:?}: {total} for {} particles",
            p.len()
        );
    }
}

#[test]
fn absurd_input_gives_clear_errors() {
    let (p, h) = water();
    let spec = GridSpec::around(&p, h, Resolution::LongestAxis(16)).unwrap();
    for bad_h in [0.0, -1.0, f32::NAN, f32::INFINITY] {
        assert!(
            matches!(
                density::density_grid(&p, &spec, Kernel::Wyvill, bad_h, 1 << 30),
                Err(DensityError::InvalidRadius { .. })
            ),
            "{bad_h}"
        );
    }
    let mut nan = p.clone();
    nan[5].y = f32::NAN;
    assert_eq!(
        density::density_grid(&nan, &spec, Kernel::Wyvill, h, 1 << 30).unwrap_err(),
        DensityError::NonFinite { index: 5 }
    );
    assert!(matches!(
        GridSpec::around(&nan, h, Resolution::LongestAxis(16)),
        Err(DensityError::NonFinite { index: 5 })
    ));
    assert_eq!(
        GridSpec::around(&[], h, Resolution::LongestAxis(16)).unwrap_err(),
        DensityError::Empty
    );
    // 10^12 cells: sized, then refused with the memory it would need, before any allocation
    let huge = GridSpec::around(&p, h, Resolution::LongestAxis(10_000)).unwrap();
    assert!(huge.cells() > 100_000_000_000);
    let e = density::density_grid(&p, &huge, Kernel::Wyvill, h, 8 << 30).unwrap_err();
    assert!(matches!(e, DensityError::TooLarge { .. }), "{e}");
    assert!(e.to_string().contains("bytes"), "{e}");
    for bad in [
        Resolution::CellSize(0.0),
        Resolution::CellSize(f32::NAN),
        Resolution::LongestAxis(1),
    ] {
        assert!(
            matches!(
                GridSpec::around(&p, h, bad),
                Err(DensityError::InvalidGrid { .. })
            ),
            "{bad:?}"
        );
    }
    assert!(matches!(
        GridSpec::around(&p, h, Resolution::CellSize(1e-30)),
        Err(DensityError::TooLarge { .. })
    ));
}
