//! Helpers shared by the fixture and generator tests.

#![allow(dead_code)]

use std::path::Path;

use serde_json::Value;

/// Structural equality with a relative tolerance on numbers, so values that went through JSON
/// (f32 printed as f64 and parsed back) still compare equal. Panics with the path of a mismatch.
pub fn assert_json_close(expected: &Value, actual: &Value, rel_tol: f64, path: &str) {
    match (expected, actual) {
        (Value::Number(a), Value::Number(b)) => {
            let (a, b) = (a.as_f64().unwrap(), b.as_f64().unwrap());
            assert!((a - b).abs() <= rel_tol * (1.0 + a.abs()), "{path}: {a} != {b}");
        }
        (Value::Array(a), Value::Array(b)) => {
            assert_eq!(a.len(), b.len(), "{path}: length");
            for (i, (x, y)) in a.iter().zip(b).enumerate() {
                assert_json_close(x, y, rel_tol, &format!("{path}[{i}]"));
            }
        }
        (Value::Object(a), Value::Object(b)) => {
            assert_eq!(a.len(), b.len(), "{path}: keys");
            for (key, x) in a {
                assert_json_close(x, &b[key], rel_tol, &format!("{path}.{key}"));
            }
        }
        _ => assert_eq!(expected, actual, "{path}"),
    }
}

/// The stored cross-language fixture at `path`, first rewritten from `computed` when
/// `REGENERATE_FIXTURES` is set (then commit the file; pytest reads the same one).
pub fn stored_fixture(path: &str, computed: &Value, text: impl Fn(&Value) -> String) -> Value {
    if std::env::var_os("REGENERATE_FIXTURES").is_some() {
        std::fs::write(path, text(computed) + "\n").unwrap();
    }
    serde_json::from_str(&std::fs::read_to_string(path).expect("fixture file")).unwrap()
}

/// Every file under `root`, relative path → bytes, sorted.
pub fn snapshot(root: &Path) -> Vec<(String, Vec<u8>)> {
    let mut out = Vec::new();
    let mut stack = vec![root.to_path_buf()];
    while let Some(dir) = stack.pop() {
        for entry in std::fs::read_dir(&dir).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                stack.push(path);
            } else {
                out.push((path.strip_prefix(root).unwrap().display().to_string(), std::fs::read(&path).unwrap()));
            }
        }
    }
    out.sort();
    out
}
