//! Reading the wrapped vector env's arrays and infos without copying them through
//! Python: what the fast path accepts, or `None` to decline.

use numpy::{PyArrayDyn, PyArrayMethods, PyUntypedArray, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList, PyTuple};
use pyo3::PyTypeInfo;

/// Whether `obj` is exactly a numpy array (not a subclass), as `type(obj) is np.ndarray`.
pub(crate) fn is_ndarray(py: Python<'_>, obj: &Bound<'_, PyAny>) -> bool {
    obj.get_type().is(PyUntypedArray::type_object(py))
}

/// Writes the numbers of `obj` (a float32 or float64 numpy array of `out.len()` numbers;
/// with `rows`, its first dimension must be `rows`) into `out` in C order, as float32:
/// what `np.asarray(obj, dtype=np.float32).reshape(-1)` holds. `None` for anything else.
pub(crate) fn float_rows(
    obj: &Bound<'_, PyAny>,
    rows: Option<usize>,
    out: &mut [f32],
) -> Option<()> {
    fn copy<T: numpy::Element + Copy>(
        a: &Bound<'_, PyArrayDyn<T>>,
        rows: Option<usize>,
        out: &mut [f32],
        cast: impl Fn(T) -> f32,
    ) -> Option<()> {
        let ro = a.try_readonly().ok()?;
        if ro.len() != out.len() || rows.is_some_and(|r| ro.shape().first() != Some(&r)) {
            return None;
        }
        match ro.as_slice() {
            Ok(xs) => out.iter_mut().zip(xs).for_each(|(o, &x)| *o = cast(x)),
            Err(_) => out
                .iter_mut()
                .zip(ro.as_array().iter())
                .for_each(|(o, &x)| *o = cast(x)),
        }
        Some(())
    }
    if let Ok(a) = obj.cast::<PyArrayDyn<f32>>() {
        copy(a, rows, out, |x| x)
    } else if let Ok(a) = obj.cast::<PyArrayDyn<f64>>() {
        copy(a, rows, out, |x| x as f32)
    } else {
        None
    }
}

/// The `n` dicts of `infos`, a list or a tuple of dicts; `None` for anything else.
pub(crate) fn info_dicts<'py>(
    infos: &Bound<'py, PyAny>,
    n: usize,
) -> Option<Vec<Bound<'py, PyDict>>> {
    let items: Vec<Bound<'py, PyAny>> = if let Ok(list) = infos.cast::<PyList>() {
        list.iter().collect()
    } else if let Ok(tuple) = infos.cast::<PyTuple>() {
        tuple.iter().collect()
    } else {
        return None;
    };
    if items.len() != n {
        return None;
    }
    items
        .into_iter()
        .map(|i| i.cast_into::<PyDict>().ok())
        .collect()
}
