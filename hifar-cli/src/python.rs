//! The embedded CPython interpreter: the ONLY module that touches pyo3.
//!
//! hifar links libpython (pyo3 `auto-initialize`) and, once per process, points the interpreter
//! at the virtual environment that `hifar setup` created: the base installation's
//! site-packages are removed from `sys.path` and the venv's are added with `site.addsitedir`
//! (so the `.pth` file of the editable `jax_env` install is honoured), which is what a
//! `bin/python` of that venv would see. Everything crosses the boundary as JSON-like values
//! (dict/list/str/float/int/bool/None), converted here from and to [`serde_json::Value`],
//! except bulk numbers: a result's NumPy float arrays are read through the buffer protocol in
//! one copy ([`Facade::call_with_arrays`]) rather than value by value.

use std::collections::BTreeMap;
use std::ffi::CString;
use std::path::{Path, PathBuf};
use std::sync::{Mutex, OnceLock};

use pyo3::buffer::PyUntypedBuffer;
use pyo3::prelude::*;
use pyo3::types::{PyBool, PyCFunction, PyDict, PyFloat, PyInt, PyList, PyString, PyTuple};
use serde_json::{Map, Number, Value};

/// Helpers that run inside the interpreter (environment, output redirection, tracebacks).
const BOOTSTRAP: &str = r#"
import os, site, sys, traceback

def base_info():
  return {
    "version": "%d.%d.%d" % sys.version_info[:3],
    "major_minor": "%d.%d" % sys.version_info[:2],
    "base_prefix": sys.base_prefix,
  }

def activate(venv, site_dir, cache_dir):
  # Embedded interpreters have no argv; absl (used by brax/jax) reads sys.argv[0].
  if not getattr(sys, "argv", None):
    sys.argv = ["hifar"]
  base = set(os.path.realpath(p) for p in site.getsitepackages())
  base.add(os.path.realpath(site.getusersitepackages()))
  sys.path[:] = [p for p in sys.path if os.path.realpath(p) not in base]
  site.addsitedir(site_dir)
  sys.prefix = sys.exec_prefix = venv
  sys.executable = os.path.join(venv, "bin", "python")
  os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", cache_dir)
  # XLA's C++ logs one warning per executable loaded from that cache ("Assume version
  # compatibility"); errors still show.
  os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")

def release_signals():
  import signal
  for sig in (signal.SIGINT, signal.SIGTERM):
    signal.signal(sig, signal.SIG_DFL)

def redirect_output(path):
  stream = open(path, "a", buffering=1, encoding="utf-8", errors="replace")
  previous = {id(s) for s in (sys.stdout, sys.stderr, sys.__stdout__, sys.__stderr__)}
  sys.stdout = stream
  sys.stderr = stream
  # Logging handlers made at import time (absl's, for one) hold the old stream object.
  import logging
  loggers = [logging.getLogger()] + [
      l for l in logging.Logger.manager.loggerDict.values() if isinstance(l, logging.Logger)]
  for logger in loggers:
    for handler in logger.handlers:
      if isinstance(handler, logging.StreamHandler) and id(handler.stream) in previous:
        handler.setStream(stream)

def describe(exc, tb):
  if tb is not None:
    exc = exc.with_traceback(tb)
  only = "".join(traceback.format_exception_only(exc)).strip().splitlines()
  summary = only[-1] if only else type(exc).__name__
  return summary, "".join(traceback.format_exception(exc))
"#;

/// A Python exception: its last line for the terminal, the full traceback for the log.
#[derive(Debug, thiserror::Error)]
#[error("{summary}")]
pub struct PythonError {
    pub summary: String,
    pub traceback: String,
}

impl PythonError {
    fn from_pyerr(py: Python<'_>, err: PyErr) -> PythonError {
        let described = bootstrap(py).and_then(|module| {
            let (summary, traceback): (String, String) =
                module.getattr("describe")?.call1((err.value(py), err.traceback(py)))?.extract()?;
            Ok((summary, traceback))
        });
        match described {
            Ok((summary, traceback)) => PythonError { summary, traceback },
            Err(_) => PythonError { summary: err.to_string(), traceback: err.to_string() },
        }
    }

    fn msg(summary: impl Into<String>) -> PythonError {
        let summary = summary.into();
        PythonError { traceback: summary.clone(), summary }
    }

    /// Appends the traceback to `log` (best effort) and returns the path for the message.
    pub fn write_traceback(&self, log: &Path) -> std::io::Result<()> {
        use std::io::Write;
        if let Some(dir) = log.parent() {
            std::fs::create_dir_all(dir)?;
        }
        let mut file = std::fs::OpenOptions::new().create(true).append(true).open(log)?;
        writeln!(file, "{}", self.traceback.trim_end())
    }
}

type PyOutcome<T> = Result<T, PythonError>;

fn bootstrap(py: Python<'_>) -> PyResult<Bound<'_, PyModule>> {
    static MODULE: OnceLock<Py<PyModule>> = OnceLock::new();
    if let Some(module) = MODULE.get() {
        return Ok(module.bind(py).clone());
    }
    let code = CString::new(BOOTSTRAP).expect("bootstrap has no NUL");
    let module = PyModule::from_code(py, &code, c"<hifar-bootstrap>", c"_hifar_bootstrap")?;
    let _ = MODULE.set(module.clone().unbind());
    Ok(module)
}

/// What the linked interpreter reports about itself, before any venv is involved.
#[derive(Debug, Clone)]
pub struct BaseInfo {
    /// e.g. "3.11.7".
    pub version: String,
    /// e.g. "3.11": the venv's `lib/pythonX.Y` must match.
    pub major_minor: String,
    /// The base installation (`sys.base_prefix`), where `bin/pythonX.Y` normally lives.
    pub base_prefix: PathBuf,
}

/// Version and location of the embedded interpreter (initializes it if needed).
pub fn base_info() -> PyOutcome<BaseInfo> {
    Python::attach(|py| {
        let result = (|| -> PyResult<Value> {
            let info = bootstrap(py)?.getattr("base_info")?.call0()?;
            to_json(&info)
        })()
        .map_err(|err| PythonError::from_pyerr(py, err))?;
        let field = |key: &str| info_str(&result, key);
        Ok(BaseInfo {
            version: field("version")?,
            major_minor: field("major_minor")?,
            base_prefix: PathBuf::from(field("base_prefix")?),
        })
    })
}

fn info_str(value: &Value, key: &str) -> PyOutcome<String> {
    value
        .get(key)
        .and_then(Value::as_str)
        .map(str::to_owned)
        .ok_or_else(|| PythonError::msg(format!("interpreter info lacks {key}")))
}

/// The `site-packages` directory of a venv for the embedded interpreter's version.
pub fn venv_site_packages(venv: &Path, major_minor: &str) -> PathBuf {
    venv.join("lib").join(format!("python{major_minor}")).join("site-packages")
}

/// Handle on `jax_env.facade` inside the activated interpreter.
pub struct Facade {
    module: Py<PyModule>,
}

static ACTIVE_VENV: OnceLock<PathBuf> = OnceLock::new();

/// Points the interpreter at `venv` (once per process) and imports `jax_env.facade`, with
/// Python's output going to `output_log` (see [`redirect_output`]) from the first import on.
///
/// `cache_dir` becomes `JAX_COMPILATION_CACHE_DIR` unless the environment already sets it.
pub fn activate(venv: &Path, cache_dir: &Path, output_log: &Path) -> PyOutcome<Facade> {
    let info = base_info()?;
    let site_dir = venv_site_packages(venv, &info.major_minor);
    if !site_dir.is_dir() {
        return Err(PythonError::msg(format!(
            "{} has no {} (hifar embeds Python {}); run `hifar setup --force`",
            venv.display(),
            site_dir.strip_prefix(venv).unwrap_or(&site_dir).display(),
            info.major_minor
        )));
    }
    Python::attach(|py| {
        let run = || -> PyResult<Py<PyModule>> {
            match ACTIVE_VENV.get() {
                Some(active) if active != venv => {
                    return Err(pyo3::exceptions::PyRuntimeError::new_err(format!(
                        "interpreter already uses {}",
                        active.display()
                    )));
                }
                Some(_) => {}
                None => {
                    bootstrap(py)?.getattr("activate")?.call1((
                        path_str(venv),
                        path_str(&site_dir),
                        path_str(cache_dir),
                    ))?;
                    let _ = ACTIVE_VENV.set(venv.to_path_buf());
                }
            }
            if let Some(dir) = output_log.parent() {
                let _ = std::fs::create_dir_all(dir);
            }
            bootstrap(py)?.getattr("redirect_output")?.call1((path_str(output_log),))?;
            Ok(PyModule::import(py, "jax_env.facade")?.unbind())
        };
        run().map(|module| Facade { module }).map_err(|err| PythonError::from_pyerr(py, err))
    })
}

/// Sends Python's `sys.stdout`/`sys.stderr` to `log` (appending) so that prints and warnings of
/// the training code do not tear the progress bar.
pub fn redirect_output(log: &Path) -> PyOutcome<()> {
    Python::attach(|py| {
        bootstrap(py)
            .and_then(|module| module.getattr("redirect_output")?.call1((path_str(log),)).map(drop))
            .map_err(|err| PythonError::from_pyerr(py, err))
    })
}

/// Gives SIGINT and SIGTERM back to Rust. The embedded interpreter installs its own SIGINT
/// handler (raising `KeyboardInterrupt` in the training loop), and a handler registered after
/// it would chain to it; with both reset to the default first, a handler installed next (see
/// `train`) is the only one.
pub fn release_signals() -> PyOutcome<()> {
    Python::attach(|py| {
        bootstrap(py)
            .and_then(|module| module.getattr("release_signals")?.call0().map(drop))
            .map_err(|err| PythonError::from_pyerr(py, err))
    })
}

fn path_str(path: &Path) -> String {
    path.to_string_lossy().into_owned()
}

impl Facade {
    /// Calls `jax_env.facade.<name>(*args)` with JSON-like arguments.
    pub fn call(&self, name: &str, args: &[Value]) -> PyOutcome<Value> {
        Python::attach(|py| {
            let run = || -> PyResult<Value> {
                let args: Vec<Bound<'_, PyAny>> =
                    args.iter().map(|arg| to_py(py, arg)).collect::<PyResult<_>>()?;
                let args = PyTuple::new(py, args)?;
                let result = self.module.bind(py).getattr(name)?.call1(args)?;
                to_json(&result)
            };
            run().map_err(|err| PythonError::from_pyerr(py, err))
        })
    }

    /// `facade.<name>(request, callback)`: `callback` sees every progress dict Python reports
    /// and answers with a word the function understands ("continue", "finish", "interrupt").
    pub fn call_with_progress<F>(&self, name: &str, request: &Value, callback: F) -> PyOutcome<Value>
    where
        F: FnMut(Value) -> String + Send + 'static,
    {
        let callback = Mutex::new(callback);
        Python::attach(|py| {
            let run = || -> PyResult<Value> {
                let function = PyCFunction::new_closure(
                    py,
                    Some(c"hifar_progress"),
                    Some(c"Progress callback of the hifar CLI."),
                    move |args: &Bound<'_, PyTuple>, _kwargs: Option<&Bound<'_, PyDict>>| {
                        let progress = to_json(&args.get_item(0)?)?;
                        let mut callback = callback.lock().unwrap_or_else(|p| p.into_inner());
                        PyResult::Ok((callback)(progress))
                    },
                )?;
                let result = self.module.bind(py).getattr(name)?.call1((to_py(py, request)?, function))?;
                to_json(&result)
            };
            run().map_err(|err| PythonError::from_pyerr(py, err))
        })
    }
}

/// A float array handed over by Python: its shape and its values in C (row-major) order.
#[derive(Debug, Clone, PartialEq)]
pub struct Array<T> {
    pub shape: Vec<usize>,
    pub data: Vec<T>,
}

/// A float array of either width, as Python computed it (nothing is rounded on the way).
#[derive(Debug, Clone, PartialEq)]
pub enum FloatArray {
    F32(Array<f32>),
    F64(Array<f64>),
}

impl FloatArray {
    pub fn shape(&self) -> &[usize] {
        match self {
            FloatArray::F32(a) => &a.shape,
            FloatArray::F64(a) => &a.shape,
        }
    }

    pub fn dtype(&self) -> &'static str {
        match self {
            FloatArray::F32(_) => "float32",
            FloatArray::F64(_) => "float64",
        }
    }
}

/// The float arrays of a result, by key.
pub type Arrays = BTreeMap<String, FloatArray>;

impl Facade {
    /// `jax_env.facade.<name>(*args)` for a function that returns a dict: its float32 and
    /// float64 arrays (anything exposing the buffer protocol with such items, i.e. NumPy
    /// arrays) come back as [`Arrays`], every other entry as JSON.
    pub fn call_with_arrays(&self, name: &str, args: &[Value]) -> PyOutcome<(Value, Arrays)> {
        Python::attach(|py| {
            let run = || -> PyResult<(Value, Arrays)> {
                let args: Vec<Bound<'_, PyAny>> =
                    args.iter().map(|arg| to_py(py, arg)).collect::<PyResult<_>>()?;
                let result = self.module.bind(py).getattr(name)?.call1(PyTuple::new(py, args)?)?;
                let dict = result.cast::<PyDict>().map_err(|_| {
                    pyo3::exceptions::PyTypeError::new_err(format!("facade.{name} returned no dict"))
                })?;
                let (mut rest, mut arrays) = (Map::new(), Arrays::new());
                for (key, item) in dict.iter() {
                    let key: String = key.extract()?;
                    match float_array(&item)? {
                        Some(array) => {
                            arrays.insert(key, array);
                        }
                        None => {
                            rest.insert(key, to_json(&item)?);
                        }
                    }
                }
                Ok((Value::Object(rest), arrays))
            };
            run().map_err(|err| PythonError::from_pyerr(py, err))
        })
    }
}

/// The object's values in one copy when it exposes the buffer protocol with float32 or float64
/// items (a NumPy array of either dtype, contiguous or not), else None.
fn float_array(obj: &Bound<'_, PyAny>) -> PyResult<Option<FloatArray>> {
    if obj.cast::<PyString>().is_ok() || obj.is_none() {
        return Ok(None);
    }
    let Ok(buffer) = PyUntypedBuffer::get(obj) else {
        return Ok(None);
    };
    let py = obj.py();
    let shape = buffer.shape().to_vec();
    if let Ok(typed) = buffer.as_typed::<f32>() {
        return Ok(Some(FloatArray::F32(Array { shape, data: typed.to_vec(py)? })));
    }
    if let Ok(typed) = buffer.as_typed::<f64>() {
        return Ok(Some(FloatArray::F64(Array { shape, data: typed.to_vec(py)? })));
    }
    Ok(None)
}

/// Converts a JSON value into the matching Python object.
fn to_py<'py>(py: Python<'py>, value: &Value) -> PyResult<Bound<'py, PyAny>> {
    Ok(match value {
        Value::Null => py.None().into_bound(py),
        Value::Bool(b) => PyBool::new(py, *b).to_owned().into_any(),
        Value::Number(n) => {
            if let Some(i) = n.as_i64() {
                i.into_pyobject(py)?.into_any()
            } else if let Some(u) = n.as_u64() {
                u.into_pyobject(py)?.into_any()
            } else {
                PyFloat::new(py, n.as_f64().unwrap_or(f64::NAN)).into_any()
            }
        }
        Value::String(s) => PyString::new(py, s).into_any(),
        Value::Array(items) => {
            let items: Vec<Bound<'py, PyAny>> =
                items.iter().map(|item| to_py(py, item)).collect::<PyResult<_>>()?;
            PyList::new(py, items)?.into_any()
        }
        Value::Object(map) => {
            let dict = PyDict::new(py);
            for (key, item) in map {
                dict.set_item(key, to_py(py, item)?)?;
            }
            dict.into_any()
        }
    })
}

/// Converts a JSON-like Python object into a JSON value. NumPy scalars and arrays are accepted
/// (through `float()`/`tolist()`); NaN and infinities become `null`, as JSON has neither.
fn to_json(obj: &Bound<'_, PyAny>) -> PyResult<Value> {
    if obj.is_none() {
        return Ok(Value::Null);
    }
    if let Ok(b) = obj.cast::<PyBool>() {
        return Ok(Value::Bool(b.is_true()));
    }
    if obj.cast::<PyInt>().is_ok() {
        if let Ok(i) = obj.extract::<i64>() {
            return Ok(Value::from(i));
        }
        if let Ok(u) = obj.extract::<u64>() {
            return Ok(Value::from(u));
        }
        return Ok(float_value(obj.extract::<f64>()?));
    }
    if let Ok(f) = obj.cast::<PyFloat>() {
        return Ok(float_value(f.value()));
    }
    if let Ok(s) = obj.cast::<PyString>() {
        return Ok(Value::String(s.to_str()?.to_owned()));
    }
    if let Ok(dict) = obj.cast::<PyDict>() {
        let mut map = Map::new();
        for (key, item) in dict.iter() {
            let key = match key.cast::<PyString>() {
                Ok(s) => s.to_str()?.to_owned(),
                Err(_) => key.str()?.to_str()?.to_owned(),
            };
            map.insert(key, to_json(&item)?);
        }
        return Ok(Value::Object(map));
    }
    if let Ok(list) = obj.cast::<PyList>() {
        return list.iter().map(|item| to_json(&item)).collect::<PyResult<_>>().map(Value::Array);
    }
    if let Ok(tuple) = obj.cast::<PyTuple>() {
        return tuple.iter().map(|item| to_json(&item)).collect::<PyResult<_>>().map(Value::Array);
    }
    if obj.hasattr("tolist")? {
        return to_json(&obj.call_method0("tolist")?);
    }
    if obj.hasattr("__fspath__")? {
        return to_json(&obj.call_method0("__fspath__")?);
    }
    if obj.hasattr("__float__")? {
        return Ok(float_value(obj.extract::<f64>()?));
    }
    Err(pyo3::exceptions::PyTypeError::new_err(format!(
        "cannot pass a {} to hifar (expected JSON-like values)",
        obj.get_type().name()?
    )))
}

fn float_value(f: f64) -> Value {
    Number::from_f64(f).map(Value::Number).unwrap_or(Value::Null)
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn json_round_trips_through_python() {
        let value = json!({
            "a": [1, -2, 3.5, true, null, "x"],
            "big": u64::MAX,
            "nested": {"k": [[0.25, 1e-30]]}
        });
        let back = Python::attach(|py| to_json(&to_py(py, &value).unwrap()).unwrap());
        assert_eq!(back, value);
    }

    #[test]
    fn nan_becomes_null_and_tuples_become_lists() {
        let back = Python::attach(|py| {
            let obj = py.eval(c"(float('nan'), 1, (2, 3))", None, None).unwrap();
            to_json(&obj).unwrap()
        });
        assert_eq!(back, json!([null, 1, [2, 3]]));
    }

    #[test]
    fn float_arrays_are_read_whole_with_their_shape_and_width() {
        let (f32s, f64s, strided, ints) = Python::attach(|py| {
            let array = |code: &std::ffi::CStr| float_array(&py.eval(code, None, None).unwrap()).unwrap();
            // memoryview.cast gives typed, shaped buffers without NumPy.
            (
                array(c"memoryview(__import__('array').array('f', [0.1, 2, 3, 4, 5, 6]).tobytes()).cast('f', [2, 3])"),
                array(c"memoryview(__import__('array').array('d', [0.1, 2]).tobytes()).cast('d')"),
                array(c"memoryview(__import__('array').array('d', [1, 2, 3, 4])).cast('B').cast('d')[::2]"),
                array(c"memoryview(__import__('array').array('i', [1, 2]))"),
            )
        });
        assert_eq!(f32s, Some(FloatArray::F32(Array { shape: vec![2, 3], data: vec![0.1f32, 2.0, 3.0, 4.0, 5.0, 6.0] })));
        assert_eq!(f64s, Some(FloatArray::F64(Array { shape: vec![2], data: vec![0.1, 2.0] })));
        assert_eq!(strided, Some(FloatArray::F64(Array { shape: vec![2], data: vec![1.0, 3.0] })));
        assert_eq!(ints, None, "integer buffers stay JSON");
    }

    #[test]
    fn exceptions_keep_summary_and_traceback() {
        let err = Python::attach(|py| {
            let err = py.run(c"def f():\n  raise ValueError('bad thing')\nf()", None, None);
            PythonError::from_pyerr(py, err.unwrap_err())
        });
        assert_eq!(err.summary, "ValueError: bad thing");
        assert!(err.traceback.contains("Traceback"), "{}", err.traceback);
        assert!(err.traceback.contains("in f"), "{}", err.traceback);
    }
}
