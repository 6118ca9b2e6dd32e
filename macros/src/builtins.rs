//! What the macro calls by a fixed name: the operators and component access, each a rule of
//! `adflex_runtime::__codegen` (`mul`, `adj_mul`, `tan_mul`, ...).
//!
//! The builtin *functions* (`sqrt`, `dot`, `lerp`, ...) are not listed here: they are items of
//! the runtime (`adflex_runtime::math::items`, the one list of them), and a call `f(..)` in a
//! kernel is emitted as a call of whatever `f` names in the user's scope, so that a user's
//! `#[diff_func] fn lerp` is called where Rust says it is, not replaced by the builtin.

/// `(name, arity)` of every operation the macro emits by name.
pub const BUILTINS: &[(&str, usize)] = &[
    // arithmetic (what the operators lower to; also callable by name)
    ("add", 2),
    ("sub", 2),
    ("mul", 2),
    ("div", 2),
    ("neg", 1),
    ("rem", 2),
    // components (what `v.x`, `v[k]` and `v.x = e` lower to)
    ("extract", 2),
    ("replace", 3),
];

/// The arity of builtin `name`, if it is one.
pub fn arity(name: &str) -> Option<usize> {
    BUILTINS.iter().find(|(n, _)| *n == name).map(|(_, a)| *a)
}

/// For a method call the kernel language does not have, the builtin to call instead.
pub fn method_hint(method: &str) -> Option<&'static str> {
    Some(match method {
        "norm" | "magnitude" => "length(v)",
        "norm_squared" | "magnitude_squared" => "length_sq(v)",
        "normalize" | "normalized" => "normalize(v)",
        "dot" => "dot(a, b)",
        "cross" => "cross(a, b)",
        "transpose" => "transpose(m)",
        "determinant" => "determinant(m)",
        "try_inverse" | "inverse" => "inverse(m)",
        "trace" => "trace(m)",
        "sqrt" => "sqrt(x)",
        "sin" => "sin(x)",
        "cos" => "cos(x)",
        "tan" => "tan(x)",
        "acos" => "acos(x)",
        "asin" => "asin(x)",
        "atan2" => "atan2(y, x)",
        "exp" => "exp(x)",
        "ln" => "ln(x)",
        "powf" => "pow(x, y)",
        "powi" => "powi(x, n)",
        "abs" => "abs(x)",
        "signum" => "sign(x)",
        "min" => "min(a, b)",
        "max" => "max(a, b)",
        "clamp" => "clamp(x, lo, hi)",
        "floor" => "floor(x)",
        "ceil" => "ceil(x)",
        "round" => "round(x)",
        "component_mul" => "cw_mul(a, b)",
        "component_div" => "cw_div(a, b)",
        _ => return None,
    })
}
