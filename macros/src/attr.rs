//! Arguments of `#[diff_kernel(..)]` and `#[diff_func(..)]`.

use proc_macro2::TokenStream;
use syn::parse::Parser;
use syn::spanned::Spanned;

use crate::{Errors, Kind};

#[derive(Default)]
pub struct Attr {
    /// `crate = path`: where the runtime is (default: found from Cargo.toml).
    pub krate: Option<syn::Path>,
    /// `adjoint = path`: a hand-written adjoint (funcs only).
    pub adjoint: Option<syn::Path>,
    /// `tangent = path`: a hand-written tangent (funcs only).
    pub tangent: Option<syn::Path>,
    /// `dual_safe`: the custom adjoint and tangent compute in the arguments' own scalar, so
    /// they may run in `Dual` (Hessian-vector products).
    pub dual_safe: bool,
}

impl Attr {
    pub fn parse(args: TokenStream, kind: Kind, errors: &mut Errors) -> Attr {
        let mut attr = Attr::default();
        let parser = syn::meta::parser(|meta| {
            let key = meta
                .path
                .get_ident()
                .map(|i| i.to_string())
                .unwrap_or_default();
            match key.as_str() {
                "crate" => {
                    let s: syn::LitStr = meta.value()?.parse()?;
                    attr.krate = Some(s.parse()?);
                }
                "adjoint" | "tangent" if kind == Kind::Func => {
                    let p: syn::Path = meta.value()?.parse()?;
                    if key == "adjoint" {
                        attr.adjoint = Some(p);
                    } else {
                        attr.tangent = Some(p);
                    }
                }
                "dual_safe" if kind == Kind::Func => attr.dual_safe = true,
                "adjoint" | "tangent" => {
                    return Err(meta.error(
                        "custom derivatives belong on a #[diff_func]; call that function from the kernel",
                    ))
                }
                _ => {
                    return Err(meta.error(if kind == Kind::Kernel {
                        "unknown argument; #[diff_kernel] accepts `crate = \"path\"`"
                    } else {
                        "unknown argument; #[diff_func] accepts `adjoint = path`, `tangent = path`, \
                         `dual_safe`, `crate = \"path\"`"
                    }))
                }
            }
            Ok(())
        });
        if let Err(e) = parser.parse2(args.clone()) {
            errors.push_error(e);
        }
        if attr.adjoint.is_some() != attr.tangent.is_some() {
            errors.push(
                args.span(),
                "a custom adjoint needs a custom tangent too (and the other way round), so that \
                 forward and reverse mode agree: `#[diff_func(adjoint = my_adj, tangent = my_tan)]`",
            );
        }
        if attr.dual_safe && attr.adjoint.is_none() {
            errors.push(
                args.span(),
                "`dual_safe` declares a custom adjoint safe in `Dual`; without `adjoint = ..` the \
                 generated rules are, and it is not needed",
            );
        }
        attr
    }
}
