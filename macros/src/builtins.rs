//! The builtins of the kernel language: names the macro emits as calls into
//! `adflex_runtime::math` (with their `adj_` and `tan_` rules), and their arities.

/// `(name, arity)` of every builtin. The runtime's `math` module implements each.
pub const BUILTINS: &[(&str, usize)] = &[
    // arithmetic (also what the operators lower to)
    ("add", 2), ("sub", 2), ("mul", 2), ("div", 2), ("neg", 1), ("rem", 2),
    // scalar functions
    ("sqrt", 1), ("sin", 1), ("cos", 1), ("tan", 1), ("asin", 1), ("acos", 1), ("atan", 1),
    ("atan2", 2), ("sinh", 1), ("cosh", 1), ("tanh", 1), ("exp", 1), ("ln", 1), ("log2", 1),
    ("log10", 1), ("pow", 2), ("powi", 2), ("abs", 1), ("sign", 1), ("floor", 1), ("ceil", 1),
    ("round", 1), ("min", 2), ("max", 2), ("clamp", 3), ("lerp", 3), ("select", 3), ("step", 1),
    ("smoothstep", 3),
    // vectors
    ("dot", 2), ("cross", 2), ("length", 1), ("length_sq", 1), ("normalize", 1), ("outer", 2),
    ("cw_mul", 2), ("cw_div", 2),
    // matrices
    ("transpose", 1), ("determinant", 1), ("inverse", 1), ("trace", 1), ("ddot", 2), ("skew", 1),
    ("diag", 1),
    // constructors
    ("vec2", 2), ("vec3", 3), ("vec4", 4), ("mat22", 4), ("mat33", 9), ("mat22_cols", 2),
    ("mat33_cols", 3), ("mat22_rows", 2), ("mat33_rows", 3), ("quat", 4), ("mat22_identity", 0),
    ("mat33_identity", 0), ("quat_identity", 0),
    // quaternions
    ("quat_mul", 2), ("quat_conjugate", 1), ("quat_inverse", 1), ("quat_normalize", 1),
    ("quat_rotate", 2), ("quat_rotate_inv", 2), ("quat_from_axis_angle", 2), ("quat_to_mat33", 1),
    ("quat_length", 1),
    // components (also what `v.x`, `v[k]` and `v.x = e` lower to)
    ("extract", 2), ("replace", 3),
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
