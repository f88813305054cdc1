//! Python bindings of fluid-surfels: [`fluid_surfels::pipeline::Pipeline`] from NumPy arrays.
//!
//! Built into the wheel `fluid_surfels` by maturin (`python/pyproject.toml`); this crate is the
//! extension module `fluid_surfels._native`, which the package's `__init__.py` re-exports. The
//! library crate itself has no Python dependency.
//!
//! Conventions: arrays in are checked here (dtype, shape, rows) and refused with a `ValueError`
//! that names what was expected; everything the crate refuses becomes `fluid_surfels.Error`
//! carrying the crate's message. The work runs with the GIL released. Arrays in are read where
//! they lie when their layout is the pipeline's (C-contiguous, aligned `float32` positions and
//! masses, `uint32` ids: a [`ParticleView`] of the NumPy buffers) and converted once otherwise.
//! Arrays out are handed to NumPy without a copy (a `Vec` becomes the array's buffer; points are
//! `float32` of shape `(N, 3)`).

use std::path::{Path, PathBuf};
use std::sync::Mutex;

use fluid_surfels::io::{self, Format, ReadOptions};
use fluid_surfels::mesh::write::MeshFormat;
use fluid_surfels::pipeline::{self, Through};
use fluid_surfels::scenes::{ColumnParams, ColumnSim};
use fluid_surfels::{Attribute, ParticleSet, ParticleView, ScalarKind};
use glam::Vec3;
use numpy::{
    Element, PyArray1, PyArray2, PyArrayDescrMethods, PyArrayMethods, PyReadonlyArray1,
    PyReadonlyArray2, PyUntypedArray, PyUntypedArrayMethods,
};
use pyo3::create_exception;
use pyo3::exceptions::{PyException, PyFileExistsError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyBool, PyDict, PyFloat, PyInt, PyList, PyString, PyTuple};

create_exception!(
    fluid_surfels,
    Error,
    PyException,
    "An error of the fluid-surfels library (a file it cannot read, a particle set it cannot use, \
     work over a limit); the message is the library's."
);

/// The crate's error as `fluid_surfels.Error`: its message and the causes it does not already
/// quote (as the command line prints them).
fn crate_error(e: fluid_surfels::Error) -> PyErr {
    Error::new_err(message_of(&e))
}

fn message_of(e: &dyn std::error::Error) -> String {
    let mut message = e.to_string();
    let mut source = e.source();
    while let Some(s) = source {
        let text = s.to_string();
        if !message.contains(&text) {
            message.push_str(": ");
            message.push_str(&text);
        }
        source = s.source();
    }
    message
}

fn value_error(message: String) -> PyErr {
    PyValueError::new_err(message)
}

// ---------------------------------------------------------------------------------------------
// arrays in

/// `obj` as a NumPy array, or a `ValueError` saying what `name` must be.
fn ndarray<'py>(
    name: &str,
    obj: &Bound<'py, PyAny>,
    expected: &str,
) -> PyResult<Bound<'py, PyUntypedArray>> {
    obj.cast::<PyUntypedArray>().cloned().map_err(|_| {
        let ty = obj
            .get_type()
            .name()
            .map_or_else(|_| "?".to_string(), |n| n.to_string());
        value_error(format!(
            "`{name}` must be a NumPy array of {expected}, got a {ty} (numpy.asarray converts it)"
        ))
    })
}

/// Checks that an array has `shape` (`None` for the rows: any count, or `rows` when given).
fn check_shape(
    name: &str,
    array: &Bound<'_, PyUntypedArray>,
    columns: Option<usize>,
    rows: Option<usize>,
) -> PyResult<usize> {
    let shape = array.shape();
    let wanted = match columns {
        Some(c) => format!("(N, {c})"),
        None => "(N,)".to_string(),
    };
    let ok = match columns {
        Some(c) => shape.len() == 2 && shape[1] == c,
        None => shape.len() == 1,
    };
    if !ok {
        return Err(value_error(format!(
            "`{name}` must have shape {wanted}, got shape {}",
            shape_text(shape)
        )));
    }
    if let Some(n) = rows
        && shape[0] != n
    {
        return Err(value_error(format!(
            "`{name}` has {} rows but there are {n} particles",
            shape[0]
        )));
    }
    Ok(shape[0])
}

fn shape_text(shape: &[usize]) -> String {
    match shape {
        [n] => format!("({n},)"),
        _ => format!(
            "({})",
            shape
                .iter()
                .map(ToString::to_string)
                .collect::<Vec<_>>()
                .join(", ")
        ),
    }
}

fn dtype_name(array: &Bound<'_, PyUntypedArray>) -> String {
    array
        .dtype()
        .str()
        .map_or_else(|_| "?".to_string(), |s| s.to_string())
}

fn is<T: Element>(array: &Bound<'_, PyUntypedArray>) -> bool {
    array.dtype().is_equiv_to(&numpy::dtype::<T>(array.py()))
}

/// The array itself when its elements are aligned, else an aligned copy (NumPy makes unaligned
/// arrays from byte buffers at odd offsets; Rust may only read aligned values).
fn aligned<'py>(array: &Bound<'py, PyUntypedArray>) -> PyResult<Bound<'py, PyUntypedArray>> {
    if array.is_aligned() {
        return Ok(array.clone());
    }
    Ok(array.call_method0("copy")?.cast_into::<PyUntypedArray>()?)
}

/// The values of a float32 or float64 array of any layout, row-major, as `f32`.
fn floats(name: &str, array: &Bound<'_, PyUntypedArray>) -> PyResult<Vec<f32>> {
    let array = &aligned(array)?;
    if is::<f32>(array) {
        let a = array.cast::<numpy::PyArrayDyn<f32>>()?.readonly();
        // C-contiguous: one copy of the buffer; any other layout (as_slice also takes Fortran
        // order, whose buffer is not row-major) element by element in row-major order
        if array.is_c_contiguous()
            && let Ok(flat) = a.as_slice()
        {
            return Ok(flat.to_vec());
        }
        return Ok(a.as_array().iter().copied().collect());
    }
    if is::<f64>(array) {
        let a = array.cast::<numpy::PyArrayDyn<f64>>()?.readonly();
        return Ok(a.as_array().iter().map(|&v| v as f32).collect());
    }
    Err(value_error(format!(
        "`{name}` must have dtype float32 or float64, got {} (convert with \
         {name}.astype(numpy.float32))",
        dtype_name(array)
    )))
}

/// An `(N, 3)` float32/float64 array as points (`rows`: the particle count it must have).
fn points(name: &str, obj: &Bound<'_, PyAny>, rows: Option<usize>) -> PyResult<Vec<Vec3>> {
    let array = ndarray(name, obj, "shape (N, 3), dtype float32 or float64")?;
    check_shape(name, &array, Some(3), rows)?;
    let flat = floats(name, &array)?;
    Ok(flat
        .chunks_exact(3)
        .map(|c| Vec3::new(c[0], c[1], c[2]))
        .collect())
}

/// Integer values of one array, converted to `u32` when every value fits.
fn try_ints<T>(name: &str, array: &Bound<'_, PyUntypedArray>) -> Option<PyResult<Vec<u32>>>
where
    T: Element + Copy + TryInto<u32> + std::fmt::Display,
{
    if !is::<T>(array) {
        return None;
    }
    let a = match array.cast::<numpy::PyArrayDyn<T>>() {
        Ok(a) => a.readonly(),
        Err(e) => return Some(Err(e.into())),
    };
    let view = a.as_array();
    Some(
        view.iter()
            .enumerate()
            .map(|(i, &v)| {
                v.try_into().map_err(|_| {
                    value_error(format!(
                        "`{name}`[{i}] is {v}: ids must lie in 0..=4294967295"
                    ))
                })
            })
            .collect(),
    )
}

const IDS: &str = "shape (N,), an integer dtype";
const MASSES: &str = "shape (N,), dtype float32 or float64";

/// A `(N,)` integer array as particle ids.
fn ids(obj: &Bound<'_, PyAny>, rows: usize) -> PyResult<Vec<u32>> {
    let array = ndarray("ids", obj, IDS)?;
    check_shape("ids", &array, None, Some(rows))?;
    ids_of(&array)
}

/// The values of an integer array as ids.
fn ids_of(array: &Bound<'_, PyUntypedArray>) -> PyResult<Vec<u32>> {
    let name = "ids";
    let array = aligned(array)?;
    try_ints::<u32>(name, &array)
        .or_else(|| try_ints::<i32>(name, &array))
        .or_else(|| try_ints::<i64>(name, &array))
        .or_else(|| try_ints::<u64>(name, &array))
        .or_else(|| try_ints::<u16>(name, &array))
        .or_else(|| try_ints::<i16>(name, &array))
        .or_else(|| try_ints::<u8>(name, &array))
        .or_else(|| try_ints::<i8>(name, &array))
        .unwrap_or_else(|| {
            Err(value_error(format!(
                "`ids` must have an integer dtype (uint32, int32, int64...), got {}",
                dtype_name(&array)
            )))
        })
}

/// The particle set of `positions` and the optional per-particle arrays.
fn particle_set(
    positions: &Bound<'_, PyAny>,
    ids_in: Option<&Bound<'_, PyAny>>,
    velocities: Option<&Bound<'_, PyAny>>,
) -> PyResult<ParticleSet> {
    let mut set = ParticleSet::from_positions(points("positions", positions, None)?);
    let n = set.positions.len();
    if let Some(i) = ids_in {
        set.ids = Some(ids(i, n)?);
    }
    if let Some(v) = velocities {
        set.velocities = Some(points("velocities", v, Some(n))?);
    }
    Ok(set)
}

/// Points read where they lie (a C-contiguous, aligned float32 array: the NumPy buffer is the
/// slice the pipeline reads) or converted once (float64, strided, Fortran order).
enum PointsIn<'py> {
    Borrowed(PyReadonlyArray2<'py, f32>),
    Owned(Vec<Vec3>),
}

impl PointsIn<'_> {
    fn as_slice(&self) -> &[Vec3] {
        match self {
            // `points_in` checked that the cast succeeds
            Self::Borrowed(a) => a
                .as_slice()
                .ok()
                .and_then(|flat| bytemuck::try_cast_slice(flat).ok())
                .unwrap_or_default(),
            Self::Owned(v) => v,
        }
    }
}

/// An `(N, 3)` float32/float64 array as points, borrowed where the layout allows.
fn points_in<'py>(
    name: &str,
    obj: &Bound<'py, PyAny>,
    rows: Option<usize>,
) -> PyResult<PointsIn<'py>> {
    let array = ndarray(name, obj, "shape (N, 3), dtype float32 or float64")?;
    check_shape(name, &array, Some(3), rows)?;
    if is::<f32>(&array)
        && array.is_c_contiguous()
        && let Ok(a) = array.cast::<PyArray2<f32>>()?.try_readonly()
        && a.as_slice()
            .is_ok_and(|flat| bytemuck::try_cast_slice::<f32, Vec3>(flat).is_ok())
    {
        return Ok(PointsIn::Borrowed(a));
    }
    Ok(PointsIn::Owned(points(name, obj, rows)?))
}

/// A per-particle column read where it lies (C-contiguous, aligned, of the pipeline's type) or
/// converted once.
enum ColumnIn<'py, T: Element> {
    Borrowed(PyReadonlyArray1<'py, T>),
    Owned(Vec<T>),
}

impl<T: Element> ColumnIn<'_, T> {
    fn as_slice(&self) -> &[T] {
        match self {
            // `column_in` checked that the slice exists
            Self::Borrowed(a) => a.as_slice().unwrap_or_default(),
            Self::Owned(v) => v,
        }
    }
}

/// An `(N,)` array as a column of `T`, borrowed when it already is one, else `convert`ed.
fn column_in<'py, T: Element>(
    name: &str,
    expected: &str,
    obj: &Bound<'py, PyAny>,
    rows: usize,
    convert: impl FnOnce(&Bound<'py, PyUntypedArray>) -> PyResult<Vec<T>>,
) -> PyResult<ColumnIn<'py, T>> {
    let array = ndarray(name, obj, expected)?;
    check_shape(name, &array, None, Some(rows))?;
    if is::<T>(&array)
        && array.is_c_contiguous()
        && let Ok(a) = array.cast::<PyArray1<T>>()?.try_readonly()
        && a.as_slice().is_ok()
    {
        return Ok(ColumnIn::Borrowed(a));
    }
    Ok(ColumnIn::Owned(convert(&array)?))
}

/// The arrays of one frame, borrowed where their layout allows.
struct FrameIn<'py> {
    positions: PointsIn<'py>,
    ids: Option<ColumnIn<'py, u32>>,
    masses: Option<ColumnIn<'py, f32>>,
    /// read by the mesh's vertex velocities only
    velocities: Option<PointsIn<'py>>,
}

impl<'py> FrameIn<'py> {
    fn new(
        positions: &Bound<'py, PyAny>,
        ids: Option<&Bound<'py, PyAny>>,
        velocities: Option<&Bound<'py, PyAny>>,
        masses: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Self> {
        let positions = points_in("positions", positions, None)?;
        let n = positions.as_slice().len();
        let ids = ids
            .map(|i| column_in("ids", IDS, i, n, |a| ids_of(a)))
            .transpose()?;
        let masses = masses
            .map(|m| column_in("masses", MASSES, m, n, |a| floats("masses", a)))
            .transpose()?;
        let velocities = velocities
            .map(|v| points_in("velocities", v, Some(n)))
            .transpose()?;
        Ok(Self {
            positions,
            ids,
            masses,
            velocities,
        })
    }

    fn view(&self) -> ParticleView<'_> {
        ParticleView {
            positions: self.positions.as_slice(),
            ids: self.ids.as_ref().map(ColumnIn::as_slice),
            masses: self.masses.as_ref().map(ColumnIn::as_slice),
        }
    }
}

// ---------------------------------------------------------------------------------------------
// arrays out

/// Points as a flat `f32` buffer without copying them.
fn flat(points: Vec<Vec3>) -> Vec<f32> {
    const _: () = assert!(size_of::<Vec3>() == 3 * size_of::<f32>());
    const _: () = assert!(align_of::<Vec3>() == align_of::<f32>());
    let mut points = std::mem::ManuallyDrop::new(points);
    let (ptr, len, cap) = (points.as_mut_ptr(), points.len(), points.capacity());
    // SAFETY: glam's `Vec3` is `#[repr(C)] { x: f32, y: f32, z: f32 }`: three `f32` without
    // padding (size and alignment asserted above), so `cap` of them are `3 cap` `f32` in the same
    // allocation, with the same layout (size `12 cap`, alignment 4) for the deallocation; `len`
    // initialised points are `3 len` initialised floats. The original `Vec` is not dropped.
    unsafe { Vec::from_raw_parts(ptr.cast::<f32>(), 3 * len, 3 * cap) }
}

fn points_out(py: Python<'_>, points: Vec<Vec3>) -> PyResult<Py<PyAny>> {
    let n = points.len();
    Ok(PyArray1::from_vec(py, flat(points))
        .reshape([n, 3])?
        .into_any()
        .unbind())
}

fn vector_out<T: Element>(py: Python<'_>, values: Vec<T>) -> Py<PyAny> {
    PyArray1::from_vec(py, values).into_any().unbind()
}

fn image_out(py: Python<'_>, image: image::RgbaImage) -> PyResult<Py<PyAny>> {
    let (w, h) = image.dimensions();
    Ok(PyArray1::from_vec(py, image.into_raw())
        .reshape([h as usize, w as usize, 4])?
        .into_any()
        .unbind())
}

// ---------------------------------------------------------------------------------------------
// parameters: Python values <-> TOML values (the layout of a pipeline file)

/// A Python value as a TOML value; `None` leaves a key out. `path` names it in errors.
fn to_toml(path: &str, value: &Bound<'_, PyAny>) -> PyResult<Option<toml::Value>> {
    if value.is_none() {
        return Ok(None);
    }
    // NumPy scalars and arrays: their Python equivalents
    if !value.is_instance_of::<PyString>()
        && !value.is_instance_of::<PyList>()
        && let Ok(list) = value.call_method0("tolist")
    {
        return to_toml(path, &list);
    }
    if value.is_instance_of::<PyBool>() {
        return Ok(Some(toml::Value::Boolean(value.extract()?)));
    }
    if value.is_instance_of::<PyInt>() {
        let v: i64 = value
            .extract()
            .map_err(|_| value_error(format!("parameter `{path}`: integer out of range")))?;
        return Ok(Some(toml::Value::Integer(v)));
    }
    if value.is_instance_of::<PyFloat>() {
        return Ok(Some(toml::Value::Float(value.extract()?)));
    }
    if let Ok(s) = value.cast::<PyString>() {
        return Ok(Some(toml::Value::String(s.to_cow()?.into_owned())));
    }
    if let Ok(d) = value.cast::<PyDict>() {
        return Ok(Some(toml::Value::Table(to_table(path, d)?)));
    }
    if value.is_instance_of::<PyList>() || value.is_instance_of::<PyTuple>() {
        let mut items = Vec::new();
        for (i, item) in value.try_iter()?.enumerate() {
            let item = item?;
            let p = format!("{path}[{i}]");
            match to_toml(&p, &item)? {
                Some(v) => items.push(v),
                None => return Err(value_error(format!("parameter `{p}` is None"))),
            }
        }
        return Ok(Some(toml::Value::Array(items)));
    }
    let ty = value
        .get_type()
        .name()
        .map_or_else(|_| "?".to_string(), |n| n.to_string());
    Err(value_error(format!(
        "parameter `{path}`: a {ty} cannot be a parameter (use numbers, strings, booleans, \
         lists and dicts)"
    )))
}

fn to_table(path: &str, dict: &Bound<'_, PyDict>) -> PyResult<toml::Table> {
    let mut table = toml::Table::new();
    for (k, v) in dict.iter() {
        let key: String = k
            .extract()
            .map_err(|_| value_error(format!("parameter names must be strings (in `{path}`)")))?;
        let p = if path.is_empty() {
            key.clone()
        } else {
            format!("{path}.{key}")
        };
        if let Some(value) = to_toml(&p, &v)? {
            table.insert(key, value);
        }
    }
    Ok(table)
}

/// A TOML value as a Python value.
fn from_toml<'py>(py: Python<'py>, value: &toml::Value) -> PyResult<Bound<'py, PyAny>> {
    Ok(match value {
        toml::Value::String(s) => s.into_pyobject(py)?.into_any(),
        toml::Value::Integer(i) => i.into_pyobject(py)?.into_any(),
        toml::Value::Float(f) => float_out(*f).into_pyobject(py)?.into_any(),
        toml::Value::Boolean(b) => b.into_pyobject(py)?.to_owned().into_any(),
        toml::Value::Datetime(d) => d.to_string().into_pyobject(py)?.into_any(),
        toml::Value::Array(items) => {
            let list = PyList::empty(py);
            for item in items {
                list.append(from_toml(py, item)?)?;
            }
            list.into_any()
        }
        toml::Value::Table(table) => dict_of(py, table)?.into_any(),
    })
}

/// A float of the parameters as Python shows it: the parameters are `f32`, which TOML widens to
/// `f64` (0.05 becomes 0.05000000074505806); a value that is exactly an `f32` is given as the
/// shortest decimal that reads back to that `f32`, so that `Pipeline(**p.params)` is the same
/// pipeline and the dict shows what was given.
fn float_out(f: f64) -> f64 {
    let single = f as f32;
    if f64::from(single) == f && single.is_finite() {
        single.to_string().parse().unwrap_or(f)
    } else {
        f
    }
}

fn dict_of<'py>(py: Python<'py>, table: &toml::Table) -> PyResult<Bound<'py, PyDict>> {
    let dict = PyDict::new(py);
    for (k, v) in table {
        dict.set_item(k, from_toml(py, v)?)?;
    }
    Ok(dict)
}

fn through_of(name: &str) -> PyResult<Through> {
    Ok(match name {
        "surface" => Through::Surface,
        "refine" => Through::Refine,
        "surfels" => Through::Surfels,
        "mesh" => Through::Mesh,
        "splats" => Through::Splats,
        "frame" => Through::Frame,
        other => {
            return Err(value_error(format!(
                "`through` must be one of surface, refine, surfels, mesh, splats, frame; got {other:?}"
            )));
        }
    })
}

// ---------------------------------------------------------------------------------------------
// classes

/// The upsampled surface of one frame (stage 2).
#[pyclass(frozen, module = "fluid_surfels")]
struct Refined {
    /// (K, 3) float32: the surface points first (in the order of `Frame.surface_indices`), then
    /// each step's new points.
    #[pyo3(get)]
    positions: Py<PyAny>,
    /// (K, 3) float32 unit normals.
    #[pyo3(get)]
    normals: Py<PyAny>,
    /// (K,) uint8: the step that made each point (0 for the surface particles).
    #[pyo3(get)]
    steps: Py<PyAny>,
    /// (K,) float32: the interpolation weights (Solenthaler et al. eq. 17-19).
    #[pyo3(get)]
    weights: Py<PyAny>,
    /// (K,) float32: the splat radius of each point.
    #[pyo3(get)]
    radii: Py<PyAny>,
    /// (K,) float32: the density kernel radius of each point (the chain's grid).
    #[pyo3(get)]
    kernel_radii: Py<PyAny>,
    /// The radius after the last step.
    #[pyo3(get)]
    final_radius: f64,
    len: usize,
}

#[pymethods]
impl Refined {
    fn __len__(&self) -> usize {
        self.len
    }

    fn __repr__(&self) -> String {
        format!(
            "Refined(points={}, final_radius={})",
            self.len, self.final_radius
        )
    }
}

/// Surfels: oriented disks on the water's surface (stage 3).
#[pyclass(frozen, module = "fluid_surfels")]
struct Surfels {
    /// (M, 3) float32 centres.
    #[pyo3(get)]
    positions: Py<PyAny>,
    /// (M, 3) float32 unit normals, out of the water.
    #[pyo3(get)]
    normals: Py<PyAny>,
    /// (M,) float32 disk radii.
    #[pyo3(get)]
    radii: Py<PyAny>,
    /// The iso-value of the density grid they lie on (NaN for the `refined` source).
    #[pyo3(get)]
    iso: f64,
    len: usize,
}

#[pymethods]
impl Surfels {
    fn __len__(&self) -> usize {
        self.len
    }

    fn __repr__(&self) -> String {
        format!("Surfels(count={}, iso={})", self.len, self.iso)
    }
}

/// A triangle mesh of the iso-surface the surfels lie on (`pipeline.frame(..., mesh=True)`):
/// closed, indexed, counter-clockwise seen from outside; its vertices are the surfels.
#[pyclass(frozen, module = "fluid_surfels")]
struct Mesh {
    /// (V, 3) float32 vertex positions.
    #[pyo3(get)]
    vertices: Py<PyAny>,
    /// (V, 3) float32 unit vertex normals, out of the water.
    #[pyo3(get)]
    normals: Py<PyAny>,
    /// (F, 3) uint32 vertex indices of each triangle.
    #[pyo3(get)]
    faces: Py<PyAny>,
    /// Whether every edge is shared by two triangles, once each way.
    #[pyo3(get)]
    closed: bool,
    /// V - E + F: 2 per separate body, less 2 per handle.
    #[pyo3(get)]
    euler_characteristic: i64,
    /// (V, 3) float32 vertex velocities interpolated from the particles' (SPH cubic spline,
    /// normalised), or None when the particles had none.
    #[pyo3(get)]
    velocities: Option<Py<PyAny>>,
    len: usize,
}

#[pymethods]
impl Mesh {
    /// The number of triangles.
    fn __len__(&self) -> usize {
        self.len
    }

    fn __repr__(&self, py: Python<'_>) -> String {
        let vertices = self
            .vertices
            .bind(py)
            .len()
            .map_or_else(|_| "?".to_string(), |n| n.to_string());
        format!(
            "Mesh(vertices={vertices}, triangles={}, closed={})",
            self.len,
            if self.closed { "True" } else { "False" }
        )
    }
}

fn mesh_out(py: Python<'_>, mesh: fluid_surfels::mesh::Mesh) -> PyResult<Mesh> {
    let fluid_surfels::mesh::Topology {
        closed,
        euler_characteristic,
    } = mesh.topology();
    let len = mesh.triangles.len();
    let faces = numpy::PyArray1::from_vec(py, mesh.triangles.into_flattened())
        .reshape([len, 3])?
        .into_any()
        .unbind();
    Ok(Mesh {
        vertices: points_out(py, mesh.positions)?,
        normals: points_out(py, mesh.normals)?,
        faces,
        closed,
        euler_characteristic,
        velocities: mesh.velocities.map(|v| points_out(py, v)).transpose()?,
        len,
    })
}

/// One frame through the pipeline: every intermediate that was computed, as NumPy arrays.
#[pyclass(frozen, module = "fluid_surfels")]
struct Frame {
    /// The support radius used.
    #[pyo3(get)]
    radius: f64,
    /// Mean neighbour count at the support radius.
    #[pyo3(get)]
    mean_neighbours: f64,
    /// (N,) uint8 class of every particle: 0 interior, 1 surface, 2 isolated.
    #[pyo3(get)]
    classes: Py<PyAny>,
    /// (N,) float32 centre-of-mass offset of every particle (Solenthaler et al. eq. 2).
    #[pyo3(get)]
    offsets: Py<PyAny>,
    /// (N, 3) float32 outward normals (zero for interior and isolated particles).
    #[pyo3(get)]
    normals: Py<PyAny>,
    /// Particles (matched by id) whose surface state changed since the previous frame.
    #[pyo3(get)]
    flips: usize,
    /// (S,) uint32: the particles that were refined (surface and isolated ones, in order).
    #[pyo3(get)]
    surface_indices: Py<PyAny>,
    /// The refined surface, from `through="refine"` on (None for the `particles` source).
    #[pyo3(get)]
    refined: Option<Py<Refined>>,
    /// The surfels that are rendered, from `through="surfels"` on; through "splats" or "frame"
    /// with detail "auto" only those facing the camera (or the light) that the picture can
    /// show, unless `mesh=True`.
    #[pyo3(get)]
    surfels: Option<Py<Surfels>>,
    /// (H, W, 4) uint8 RGBA: the shaded splats (`through="splats"`) or the finished frame
    /// (`through="frame"`); None before.
    #[pyo3(get)]
    image: Option<Py<PyAny>>,
    /// Milliseconds per stage (`neighbours_ms`, `detect_ms`, ..., `total_ms`) and what the level
    /// of detail made: `detail` ("auto" or "fixed" as applied), `steps` (run), `refined_points`,
    /// `cell` (the density grid's), `surfels` and `hidden_surfels` (left out as facing away from
    /// the picture's views).
    #[pyo3(get)]
    timings: Py<PyAny>,
    /// What a user should know (a radius far off, a grid coarsened to fit the memory budget).
    #[pyo3(get)]
    warnings: Vec<String>,
    /// The triangle mesh of the surfels' iso-surface, with `mesh=True` (None otherwise, and for
    /// the renderers that draw spheres).
    #[pyo3(get)]
    mesh: Option<Py<Mesh>>,
    particles: usize,
}

#[pymethods]
impl Frame {
    fn __repr__(&self, py: Python<'_>) -> String {
        let count = |n: Option<usize>| n.map_or_else(|| "None".to_string(), |n| n.to_string());
        let refined = count(self.refined.as_ref().map(|r| r.get().len));
        let surfels = count(self.surfels.as_ref().map(|s| s.get().len));
        let image = self
            .image
            .as_ref()
            .and_then(|i| i.bind(py).getattr("shape").ok().map(|s| s.to_string()));
        format!(
            "Frame(particles={}, radius={}, refined={refined}, surfels={surfels}, image={})",
            self.particles,
            self.radius,
            image.unwrap_or_else(|| "None".into())
        )
    }
}

fn frame_out(
    py: Python<'_>,
    frame: pipeline::Frame,
    mesh: Option<fluid_surfels::mesh::Mesh>,
) -> PyResult<Frame> {
    let particles = frame.surface.classes.len();
    let surface = frame.surface;
    let classes: Vec<u8> = surface.classes.iter().map(|&c| c as u8).collect();
    let refined = match frame.refined {
        Some(r) => {
            let len = r.len();
            Some(Py::new(
                py,
                Refined {
                    positions: points_out(py, r.positions)?,
                    normals: points_out(py, r.normals)?,
                    steps: vector_out(py, r.steps),
                    weights: vector_out(py, r.weights),
                    radii: vector_out(py, r.radii),
                    kernel_radii: vector_out(py, r.kernel_radii),
                    final_radius: float_out(r.final_radius.into()),
                    len,
                },
            )?)
        }
        None => None,
    };
    let surfels = match (frame.surfels, frame.render_surfels.is_empty()) {
        (Some(s), _) => {
            let len = s.len();
            Some(Py::new(
                py,
                Surfels {
                    positions: points_out(py, s.positions)?,
                    normals: points_out(py, s.normals)?,
                    radii: vector_out(py, s.radii),
                    iso: float_out(s.iso.into()),
                    len,
                },
            )?)
        }
        // the refined source renders the refined points with their gap-free radii
        (None, false) => {
            let r = &frame.render_surfels;
            Some(Py::new(
                py,
                Surfels {
                    positions: points_out(py, r.iter().map(|s| s.position.into()).collect())?,
                    normals: points_out(py, r.iter().map(|s| s.normal.into()).collect())?,
                    radii: vector_out(py, r.iter().map(|s| s.radius).collect()),
                    iso: f64::NAN,
                    len: r.len(),
                },
            )?)
        }
        (None, true) => None,
    };
    let image = match (frame.finished, frame.splats) {
        (Some(f), _) => Some(image_out(py, f.image)?),
        (None, Some(s)) => Some(image_out(py, s.image)?),
        (None, None) => None,
    };
    // the milliseconds per stage and what the level of detail made (steps, points, cell,
    // surfels) in one dict
    let mut timings =
        toml::Value::try_from(frame.timings).map_err(|e| Error::new_err(e.to_string()))?;
    if let (Some(t), toml::Value::Table(d)) = (
        timings.as_table_mut(),
        toml::Value::try_from(frame.detail).map_err(|e| Error::new_err(e.to_string()))?,
    ) {
        t.extend(d);
    }
    Ok(Frame {
        radius: float_out(frame.radius.into()),
        mean_neighbours: float_out(frame.mean_neighbours.into()),
        classes: vector_out(py, classes),
        offsets: vector_out(py, surface.offsets),
        normals: points_out(py, surface.normals)?,
        flips: surface.flips,
        surface_indices: vector_out(py, frame.surface_indices),
        refined,
        surfels,
        image,
        timings: from_toml(py, &timings)?.unbind(),
        warnings: frame.warnings,
        mesh: mesh.map(|m| Py::new(py, mesh_out(py, m)?)).transpose()?,
        particles,
    })
}

/// The chain from particles to pixels, on the CPU: surface detection (with hysteresis across
/// the frames of a sequence), upsampling, density grid, surfels, EWA splats and optics.
///
/// `Pipeline(**params)` takes the keys of a pipeline file as keyword arguments, tables as dicts:
/// `Pipeline(support_radius=0.1, refine={"steps": 2}, optics={"image_size": [640, 480]})`.
/// Unset keys keep their defaults (the papers' values); unknown keys are refused.
#[pyclass(frozen, module = "fluid_surfels")]
struct Pipeline {
    inner: Mutex<pipeline::Pipeline>,
}

/// The frame's warnings through Python's `warnings` module (`UserWarning`), so that they show
/// (once per place, by default) and filters and `pytest.warns` see them; `Frame.warnings` keeps
/// them too.
fn warn(py: Python<'_>, warnings: &[String]) -> PyResult<()> {
    let category = py.get_type::<pyo3::exceptions::PyUserWarning>();
    for w in warnings {
        let text = std::ffi::CString::new(w.replace('\0', " ")).unwrap_or_default();
        PyErr::warn(py, &category, &text, 1)?;
    }
    Ok(())
}

fn pipeline_error(e: fluid_surfels::Error) -> PyErr {
    match e {
        // settings out of range are the caller's values
        fluid_surfels::Error::Pipeline(_) | fluid_surfels::Error::Surface(_) => {
            value_error(message_of(&e))
        }
        e => crate_error(e),
    }
}

impl Pipeline {
    fn with(params: pipeline::PipelineParams) -> PyResult<Self> {
        Ok(Self {
            inner: Mutex::new(pipeline::Pipeline::new(params).map_err(pipeline_error)?),
        })
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, pipeline::Pipeline> {
        // a panic inside a frame is a bug; the pipeline's state is still usable
        self.inner
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }
}

#[pymethods]
impl Pipeline {
    #[new]
    #[pyo3(signature = (**params))]
    fn new(params: Option<&Bound<'_, PyDict>>) -> PyResult<Self> {
        Self::with(params_in(params)?)
    }

    /// A pipeline from a TOML file (the format of `render --config`; relative paths are
    /// relative to the file).
    #[staticmethod]
    fn from_toml(path: PathBuf) -> PyResult<Self> {
        let params = pipeline::PipelineParams::from_toml_file(&path)
            .map_err(|e| pipeline_error(e.into()))?;
        Self::with(params)
    }

    /// Every parameter, as a dict in the layout of a pipeline file (`Pipeline(**p.params)` is
    /// the same pipeline).
    #[getter]
    fn params<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let table = self.lock().params().to_table().map_err(Error::new_err)?;
        dict_of(py, &table)
    }

    /// The support radius in use (None before the first frame when it is estimated).
    #[getter]
    fn support_radius(&self) -> Option<f64> {
        self.lock().support_radius().map(|r| float_out(r.into()))
    }

    /// Runs one frame: `positions` (N, 3) float32 or float64; `ids` (N,) integers keep the
    /// hysteresis of surface detection attached to each particle when the order changes between
    /// frames; `velocities` (N, 3) are checked but no stage reads them yet; `masses` (N,) weigh
    /// the centre of mass of surface detection (all equal when absent). `through` stops the
    /// chain early: "surface", "refine", "surfels" (default), "mesh" (the surfels and the mesh
    /// of their iso-surface, as `mesh=True` gives), "splats" (shaded splats image) or "frame"
    /// (finished image with caustics, refraction and reflection).
    ///
    /// C-contiguous float32 positions and masses and uint32 ids are read where they lie, with
    /// the GIL released: do not write to them from another thread during the call.
    #[pyo3(signature = (positions, ids=None, velocities=None, *, masses=None, through="surfels", mesh=false))]
    #[allow(clippy::too_many_arguments)]
    fn frame<'py>(
        &self,
        py: Python<'py>,
        positions: &Bound<'py, PyAny>,
        ids: Option<&Bound<'py, PyAny>>,
        velocities: Option<&Bound<'py, PyAny>>,
        masses: Option<&Bound<'py, PyAny>>,
        through: &str,
        mesh: bool,
    ) -> PyResult<Frame> {
        let through = through_of(through)?;
        let input = FrameIn::new(positions, ids, velocities, masses)?;
        let view = input.view();
        let velocities = input.velocities.as_ref().map(PointsIn::as_slice);
        let (frame, mesh) = py
            .detach(|| {
                // the mesh made in the chain where the frame stops at the surfels
                let run = if mesh && through == Through::Surfels {
                    Through::Mesh
                } else {
                    through
                };
                let mut pipeline = self.lock();
                // a mesh's vertices are its frame's surfels, moved onto the surface: every
                // one, also those the frame's picture cannot show
                pipeline.keep_hidden_surfels(mesh);
                let mut frame = pipeline.frame_through(view, run)?;
                drop(pipeline);
                let mut m = match frame.mesh.take() {
                    Some(m) => Some(m),
                    None if mesh => frame.triangulate(),
                    None => None,
                };
                if let (Some(m), Some(v)) = (&mut m, velocities) {
                    m.interpolate_velocities(view.positions, v, frame.radius)?;
                }
                Ok::<_, fluid_surfels::Error>((frame, m))
            })
            .map_err(crate_error)?;
        warn(py, &frame.warnings)?;
        frame_out(py, frame, mesh)
    }

    /// The whole chain on one frame, returning its image as an (H, W, 4) uint8 RGBA array:
    /// `image="frame"` (default) the finished frame, `image="splats"` the shaded splats.
    #[pyo3(signature = (positions, ids=None, velocities=None, *, masses=None, image="frame"))]
    fn render<'py>(
        &self,
        py: Python<'py>,
        positions: &Bound<'py, PyAny>,
        ids: Option<&Bound<'py, PyAny>>,
        velocities: Option<&Bound<'py, PyAny>>,
        masses: Option<&Bound<'py, PyAny>>,
        image: &str,
    ) -> PyResult<Py<PyAny>> {
        let through = match image {
            "frame" => Through::Frame,
            "splats" => Through::Splats,
            other => {
                return Err(value_error(format!(
                    "`image` must be \"frame\" or \"splats\", got {other:?}"
                )));
            }
        };
        let input = FrameIn::new(positions, ids, velocities, masses)?;
        let view = input.view();
        let frame = py
            .detach(|| self.lock().frame_through(view, through))
            .map_err(crate_error)?;
        warn(py, &frame.warnings)?;
        let picture = match (frame.finished, frame.splats) {
            (Some(f), _) => f.image,
            (None, Some(s)) => s.image,
            (None, None) => return Err(Error::new_err("the frame made no image")),
        };
        image_out(py, picture)
    }

    /// Fits the camera, the pool and the scene box of the sequence to the box [lo, hi] as well as
    /// to the first rendered frame's water (give the union of every frame's bounds).
    fn fit_to(&self, lo: [f32; 3], hi: [f32; 3]) -> PyResult<()> {
        self.lock()
            .fit_to(Vec3::from(lo), Vec3::from(hi))
            .map_err(pipeline_error)
    }

    /// Forgets what the sequence kept (hysteresis, estimated radius, camera and pool).
    fn reset(&self) {
        self.lock().reset();
    }

    /// The sequence's plan (support radius, camera, pool, scene box, the light's resolutions)
    /// as a dict, once a frame was rendered; None before. Another pipeline's `set_plan` takes
    /// it, so a chunk of the sequence renders with the same views.
    fn plan<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyAny>>> {
        self.lock().plan().map(|p| plan_out(py, &p)).transpose()
    }

    /// Takes a sequence's plan (a dict from `plan()` or `plan_of`, or its JSON text).
    fn set_plan(&self, plan: &Bound<'_, PyAny>) -> PyResult<()> {
        let plan = plan_in(plan)?;
        self.lock().set_plan(&plan).map_err(pipeline_error)
    }

    /// Runs surface detection (and the levels of detail) alone on a frame before the ones to
    /// draw, so that a chunk of a sequence starts with the serial run's hysteresis; `through`
    /// as the frames to come ("frame" by default).
    #[pyo3(signature = (positions, ids=None, *, masses=None, through="frame"))]
    fn warm_up<'py>(
        &self,
        py: Python<'py>,
        positions: &Bound<'py, PyAny>,
        ids: Option<&Bound<'py, PyAny>>,
        masses: Option<&Bound<'py, PyAny>>,
        through: &str,
    ) -> PyResult<()> {
        let through = through_of(through)?;
        let input = FrameIn::new(positions, ids, None, masses)?;
        let view = input.view();
        py.detach(|| self.lock().warm_up(view, through))
            .map_err(crate_error)
    }

    fn __repr__(&self) -> String {
        let p = self.lock();
        let radius = p
            .support_radius()
            .map_or_else(|| "None".to_string(), |r| r.to_string());
        format!(
            "Pipeline(source={:?}, support_radius={radius})",
            p.params().source.as_str(),
        )
    }
}

// ---------------------------------------------------------------------------------------------
// files

fn format_of(name: Option<&str>) -> PyResult<Option<Format>> {
    let Some(name) = name else { return Ok(None) };
    Format::ALL
        .into_iter()
        .find(|f| f.name() == name)
        .map(Some)
        .ok_or_else(|| {
            let names: Vec<&str> = Format::ALL.iter().map(|f| f.name()).collect();
            value_error(format!(
                "`format` must be one of {}, got {name:?}",
                names.join(", ")
            ))
        })
}

fn kind_of(array: &Bound<'_, PyUntypedArray>) -> Option<ScalarKind> {
    [
        (is::<i8>(array), ScalarKind::I8),
        (is::<u8>(array), ScalarKind::U8),
        (is::<i16>(array), ScalarKind::I16),
        (is::<u16>(array), ScalarKind::U16),
        (is::<i32>(array), ScalarKind::I32),
        (is::<u32>(array), ScalarKind::U32),
        (is::<f32>(array), ScalarKind::F32),
        (is::<f64>(array), ScalarKind::F64),
    ]
    .into_iter()
    .find_map(|(yes, kind)| yes.then_some(kind))
}

/// An extra attribute's values in the dtype it was read with.
fn attribute_out(py: Python<'_>, a: &Attribute, n: usize) -> PyResult<Py<PyAny>> {
    macro_rules! typed {
        ($t:ty) => {{
            let v: Vec<$t> = a.values.iter().map(|&x| x as $t).collect();
            PyArray1::from_vec(py, v).into_any()
        }};
    }
    let array = match a.kind {
        ScalarKind::I8 => typed!(i8),
        ScalarKind::U8 => typed!(u8),
        ScalarKind::I16 => typed!(i16),
        ScalarKind::U16 => typed!(u16),
        ScalarKind::I32 => typed!(i32),
        ScalarKind::U32 => typed!(u32),
        ScalarKind::F32 => typed!(f32),
        ScalarKind::F64 => typed!(f64),
    };
    Ok(if a.components == 1 {
        array.unbind()
    } else {
        array
            .call_method1("reshape", ((n, a.components),))?
            .unbind()
    })
}

/// Reads a particle file (PLY, legacy VTK, VTU/VTP, BGEO, XYZ, CSV, JSON; by extension unless
/// `format` names one) into a dict of NumPy arrays: `positions` (N, 3) float32 and, where the
/// file has them, `ids` (N,) uint32, `masses` (N,) float32, `velocities` and `normals` (N, 3)
/// float32, `colours` (N, 3) uint8, and `attributes`: a dict of the other per-particle
/// attributes by name, (N,) or (N, C), in the type the file stores.
#[pyfunction]
#[pyo3(signature = (path, format=None, *, memory_budget=None))]
fn read<'py>(
    py: Python<'py>,
    path: PathBuf,
    format: Option<&str>,
    memory_budget: Option<u64>,
) -> PyResult<Bound<'py, PyDict>> {
    let format = format_of(format)?;
    let mut options = ReadOptions::default();
    if let Some(b) = memory_budget {
        options.memory_budget = b;
    }
    let set = py
        .detach(|| io::read_particles_with(&path, format, &options))
        .map_err(|e| crate_error(e.into()))?;
    particles_out(py, set)
}

fn particles_out(py: Python<'_>, set: ParticleSet) -> PyResult<Bound<'_, PyDict>> {
    let n = set.len();
    let dict = PyDict::new(py);
    dict.set_item("positions", points_out(py, set.positions)?)?;
    if let Some(ids) = set.ids {
        dict.set_item("ids", vector_out(py, ids))?;
    }
    if let Some(m) = set.masses {
        dict.set_item("masses", vector_out(py, m))?;
    }
    if let Some(v) = set.velocities {
        dict.set_item("velocities", points_out(py, v)?)?;
    }
    if let Some(v) = set.normals {
        dict.set_item("normals", points_out(py, v)?)?;
    }
    if let Some(c) = set.colours {
        let flat: Vec<u8> = c.into_iter().flatten().collect();
        dict.set_item("colours", PyArray1::from_vec(py, flat).reshape([n, 3])?)?;
    }
    let attributes = PyDict::new(py);
    for a in &set.extra {
        attributes.set_item(&a.name, attribute_out(py, a, n)?)?;
    }
    dict.set_item("attributes", attributes)?;
    Ok(dict)
}

/// Writes a particle file (by extension unless `format` names one; PLY and VTK binary), with
/// the optional per-particle arrays and `attributes` (a dict of (N,) or (N, C) arrays of 8- to
/// 32-bit integers or floats, written in their own type). An existing file is replaced only with
/// `overwrite=True`; the file is written whole or not at all.
#[pyfunction]
#[pyo3(signature = (path, positions, *, ids=None, masses=None, velocities=None, normals=None,
                    colours=None, attributes=None, format=None, overwrite=false))]
#[allow(clippy::too_many_arguments)]
fn write(
    py: Python<'_>,
    path: PathBuf,
    positions: &Bound<'_, PyAny>,
    ids: Option<&Bound<'_, PyAny>>,
    masses: Option<&Bound<'_, PyAny>>,
    velocities: Option<&Bound<'_, PyAny>>,
    normals: Option<&Bound<'_, PyAny>>,
    colours: Option<&Bound<'_, PyAny>>,
    attributes: Option<&Bound<'_, PyDict>>,
    format: Option<&str>,
    overwrite: bool,
) -> PyResult<()> {
    let format = format_of(format)?;
    let mut set = particle_set(positions, ids, velocities)?;
    let n = set.len();
    if let Some(m) = masses {
        let array = ndarray("masses", m, MASSES)?;
        check_shape("masses", &array, None, Some(n))?;
        set.masses = Some(floats("masses", &array)?);
    }
    if let Some(v) = normals {
        set.normals = Some(points("normals", v, Some(n))?);
    }
    if let Some(c) = colours {
        let array = ndarray("colours", c, "shape (N, 3), dtype uint8")?;
        check_shape("colours", &array, Some(3), Some(n))?;
        if !is::<u8>(&array) {
            return Err(value_error(format!(
                "`colours` must have dtype uint8, got {}",
                dtype_name(&array)
            )));
        }
        let a = array.cast::<PyArray2<u8>>()?.readonly();
        let view = a.as_array();
        set.colours = Some(
            view.rows()
                .into_iter()
                .map(|r| [r[0], r[1], r[2]])
                .collect(),
        );
    }
    if let Some(attrs) = attributes {
        for (k, v) in attrs.iter() {
            let name: String = k
                .extract()
                .map_err(|_| value_error("attribute names must be strings".into()))?;
            let label = format!("attributes[{name:?}]");
            let array = ndarray(&label, &v, "shape (N,) or (N, C)")?;
            let shape = array.shape().to_vec();
            let components = match shape.as_slice() {
                [rows] if *rows == n => 1,
                [rows, c] if *rows == n && *c > 0 => *c,
                _ => {
                    return Err(value_error(format!(
                        "`{label}` must have shape ({n},) or ({n}, C), got shape {}",
                        shape_text(&shape)
                    )));
                }
            };
            let kind = kind_of(&array).ok_or_else(|| {
                value_error(format!(
                    "`{label}` must have an 8- to 32-bit integer or a float dtype, got {}",
                    dtype_name(&array)
                ))
            })?;
            let values: Vec<f64> = array
                .call_method1("astype", ("float64",))?
                .cast_into::<numpy::PyArrayDyn<f64>>()?
                .readonly()
                .as_array()
                .iter()
                .copied()
                .collect();
            set.extra.push(Attribute {
                name,
                kind,
                components,
                values,
            });
        }
    }
    refuse_existing(&path, overwrite)?;
    py.detach(|| io::write_particles(&path, &set, format))
        .map_err(|e| crate_error(e.into()))
}

/// `FileExistsError` for an existing `path` unless `overwrite`.
fn refuse_existing(path: &Path, overwrite: bool) -> PyResult<()> {
    if !overwrite && path.exists() {
        return Err(PyFileExistsError::new_err(format!(
            "{} exists; pass overwrite=True to replace it",
            path.display()
        )));
    }
    Ok(())
}

/// Writes a triangle mesh as binary PLY, OBJ, legacy VTK, VTK XML or USD text (by the
/// extension of `path`: .ply, .obj, .vtk, .vtu, .usda), atomically: `vertices` (V, 3), `faces` (F, 3) of vertex
/// indices, `velocities` (V, 3) when given (not in OBJ); the normals are the triangles'
/// area-weighted ones. `time`: a .usda frame of a sequence, its values time samples at that
/// time code (see `write_usd_stage`). An existing file is replaced only with `overwrite=True`.
#[pyfunction]
#[pyo3(signature = (path, vertices, faces, *, velocities=None, time=None, overwrite=false))]
fn write_mesh(
    py: Python<'_>,
    path: PathBuf,
    vertices: &Bound<'_, PyAny>,
    faces: &Bound<'_, PyAny>,
    velocities: Option<&Bound<'_, PyAny>>,
    time: Option<f64>,
    overwrite: bool,
) -> PyResult<()> {
    let positions = points("vertices", vertices, None)?;
    let velocities = velocities
        .map(|v| points("velocities", v, Some(positions.len())))
        .transpose()?;
    let array = ndarray("faces", faces, "shape (F, 3), an integer dtype")?;
    check_shape("faces", &array, Some(3), None)?;
    let flat: Vec<i64> = array
        .call_method1("astype", ("int64",))?
        .cast_into::<numpy::PyArrayDyn<i64>>()?
        .readonly()
        .as_array()
        .iter()
        .copied()
        .collect();
    if flat.iter().any(|&v| v < 0 || v > i64::from(u32::MAX)) {
        return Err(value_error(
            "`faces` must hold vertex indices from 0".into(),
        ));
    }
    let triangles: Vec<[u32; 3]> = flat
        .chunks_exact(3)
        .map(|t| [t[0] as u32, t[1] as u32, t[2] as u32])
        .collect();
    let format = MeshFormat::of_path(&path).map_err(|e| value_error(message_of(&e)))?;
    if time.is_some() && format != MeshFormat::Usda {
        return Err(value_error(format!(
            "{}: `time` is for a .usda frame of a sequence",
            path.display()
        )));
    }
    if time.is_some_and(|t| !t.is_finite()) {
        return Err(value_error("`time` must be finite".into()));
    }
    refuse_existing(&path, overwrite)?;
    let mut mesh = fluid_surfels::mesh::Mesh::new(positions, triangles)
        .map_err(|e| value_error(message_of(&e)))?;
    mesh.velocities = velocities;
    py.detach(|| match time {
        Some(t) => mesh
            .write_usda(&path, Some(t))
            .map_err(fluid_surfels::Error::from),
        None => mesh.write(&path),
    })
    .map_err(crate_error)
}

/// Reads a mesh from a .ply or .vtk file (those `write_mesh` writes, or another tool's):
/// vertices, normals (from the file, or the triangles'), velocities when the file has them,
/// faces (polygons split into triangles).
#[pyfunction]
fn read_mesh(py: Python<'_>, path: PathBuf) -> PyResult<Mesh> {
    let mesh = py
        .detach(|| fluid_surfels::mesh::Mesh::read(&path))
        .map_err(|e| match e {
            fluid_surfels::Error::InvalidArgument { .. } => value_error(message_of(&e)),
            e => crate_error(e),
        })?;
    mesh_out(py, mesh)
}

/// Writes a USD stage (.usda) that plays the .usda frames `frames` ((time code, path) pairs,
/// each written by `write_mesh(..., time=t)`) as an animation through value clips, with its
/// manifest `<stem>.manifest.usda` beside it; `fps` frames per second. Atomically; an
/// existing stage is replaced only with `overwrite=True`.
#[pyfunction]
#[pyo3(signature = (path, frames, *, fps=24.0, overwrite=false))]
fn write_usd_stage(
    path: PathBuf,
    frames: Vec<(f64, PathBuf)>,
    fps: f64,
    overwrite: bool,
) -> PyResult<()> {
    refuse_existing(&path, overwrite)?;
    fluid_surfels::mesh::write::write_usd_stage(&path, &frames, fps).map_err(crate_error)
}

/// The particles of the built-in `column` scene (a collapsing water column, 2,880 particles,
/// simulated), frames 0 to `last`: a list of dicts with `positions`, `ids`, `masses` and
/// `velocities`, one per frame.
#[pyfunction]
fn column_frames(py: Python<'_>, last: usize) -> PyResult<Bound<'_, PyList>> {
    let sets = py
        .detach(|| -> Result<Vec<ParticleSet>, fluid_surfels::Error> {
            ColumnParams::check_frame(last)?;
            let mut sim = ColumnSim::new(ColumnParams::default())?;
            let mut sets = Vec::with_capacity(last + 1);
            loop {
                sets.push(sim.particles().clone());
                if sim.frame() >= last {
                    return Ok(sets);
                }
                sim.step_frame();
            }
        })
        .map_err(crate_error)?;
    let list = PyList::empty(py);
    for set in sets {
        let d = particles_out(py, set)?;
        d.del_item("attributes")?;
        list.append(d)?;
    }
    Ok(list)
}

/// The parameters of the main job on the `column` scene (the simulation's support radius, the
/// tank as the pool, its camera), as a dict for `Pipeline(**column_params())`.
#[pyfunction]
fn column_params(py: Python<'_>) -> PyResult<Bound<'_, PyDict>> {
    let table = pipeline::column_params()
        .to_table()
        .map_err(Error::new_err)?;
    dict_of(py, &table)
}

// ---------------------------------------------------------------------------------------------
// sequences in chunks

/// A plan as a dict (through its JSON).
fn plan_out<'py>(py: Python<'py>, plan: &pipeline::SequencePlan) -> PyResult<Bound<'py, PyAny>> {
    let text = serde_json::to_string(plan).map_err(|e| Error::new_err(e.to_string()))?;
    py.import("json")?.call_method1("loads", (text,))
}

/// A plan from a dict or its JSON text, checked.
fn plan_in(plan: &Bound<'_, PyAny>) -> PyResult<pipeline::SequencePlan> {
    let text: String = match plan.extract::<String>() {
        Ok(t) => t,
        Err(_) => plan
            .py()
            .import("json")?
            .call_method1("dumps", (plan,))?
            .extract()?,
    };
    let plan: pipeline::SequencePlan = serde_json::from_str(&text)
        .map_err(|e| value_error(format!("not a sequence plan: {e}")))?;
    plan.validate()
        .map_err(|e| value_error(format!("unusable sequence plan: {e}")))?;
    Ok(plan)
}

/// Pipeline parameters from the keyword dict of `Pipeline(**params)`.
fn params_in(params: Option<&Bound<'_, PyDict>>) -> PyResult<pipeline::PipelineParams> {
    let table = match params {
        Some(d) => to_table("", d)?,
        None => toml::Table::new(),
    };
    pipeline::PipelineParams::from_table(table, Path::new("."))
        .map_err(|e| value_error(format!("invalid pipeline parameters: {e}")))
}

/// A file pattern holding `{}` or `{:04}` for the frame number.
fn pattern_in(pattern: &str) -> PyResult<fluid_surfels::sequence::FramePattern> {
    fluid_surfels::sequence::FramePattern::parse(pattern)
        .map_err(|e| value_error(e.to_string()))?
        .ok_or_else(|| value_error(format!("`{pattern}` needs a {{}} for the frame number")))
}

/// The plan of a sequence of files: frame `first` of `pattern` drawn as a finished frame by a
/// pipeline of `params` (the camera, pool and scene box fitted to it), as a dict.
#[pyfunction]
#[pyo3(signature = (pattern, first, params=None))]
fn plan_of<'py>(
    py: Python<'py>,
    pattern: &str,
    first: usize,
    params: Option<&Bound<'py, PyDict>>,
) -> PyResult<Bound<'py, PyAny>> {
    let pattern = pattern_in(pattern)?;
    let params = params_in(params)?;
    let plan = py
        .detach(|| pipeline::plan_of(&pattern, first, &params, None))
        .map_err(crate_error)?;
    plan_out(py, &plan)
}

/// One chunk of a sequence of files (the task of `fluid_surfels.cluster`): a pipeline of
/// `params` takes `plan`, warms up on the frames `warmup`, and writes the finished frame of
/// each of `frames` to `out/frame_NNNN.png` atomically; a frame that fails is reported and the
/// others are written; with `skip_existing` existing PNGs are kept. Returns a dict: `written`,
/// `skipped`, `failed` (pairs of frame and error), `warmup_failed`, `seconds`.
#[pyfunction]
#[pyo3(signature = (pattern, frames, out, *, warmup=Vec::new(), plan=None, params=None, skip_existing=true))]
#[allow(clippy::too_many_arguments)]
fn render_chunk<'py>(
    py: Python<'py>,
    pattern: &str,
    frames: Vec<usize>,
    out: PathBuf,
    warmup: Vec<usize>,
    plan: Option<&Bound<'py, PyAny>>,
    params: Option<&Bound<'py, PyDict>>,
    skip_existing: bool,
) -> PyResult<Bound<'py, PyAny>> {
    let pattern = pattern_in(pattern)?;
    let params = params_in(params)?;
    let plan = plan.map(plan_in).transpose()?;
    let report = py
        .detach(|| {
            pipeline::render_chunk(
                &pattern,
                (&warmup, &frames),
                &out,
                &params,
                plan.as_ref(),
                skip_existing,
            )
        })
        .map_err(crate_error)?;
    let text = serde_json::to_string(&report).map_err(|e| Error::new_err(e.to_string()))?;
    py.import("json")?.call_method1("loads", (text,))
}

/// The extension module `fluid_surfels._native`.
#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("Error", m.py().get_type::<Error>())?;
    m.add_class::<Pipeline>()?;
    m.add_class::<Frame>()?;
    m.add_class::<Refined>()?;
    m.add_class::<Surfels>()?;
    m.add_class::<Mesh>()?;
    m.add_function(wrap_pyfunction!(read, m)?)?;
    m.add_function(wrap_pyfunction!(write, m)?)?;
    m.add_function(wrap_pyfunction!(write_mesh, m)?)?;
    m.add_function(wrap_pyfunction!(read_mesh, m)?)?;
    m.add_function(wrap_pyfunction!(write_usd_stage, m)?)?;
    m.add_function(wrap_pyfunction!(column_frames, m)?)?;
    m.add_function(wrap_pyfunction!(column_params, m)?)?;
    m.add_function(wrap_pyfunction!(plan_of, m)?)?;
    m.add_function(wrap_pyfunction!(render_chunk, m)?)?;
    let formats: Vec<&str> = Format::ALL.iter().map(|f| f.name()).collect();
    m.add("FORMATS", formats)?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
