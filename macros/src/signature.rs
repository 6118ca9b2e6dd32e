//! What the macro reads from a fn's signature: its parameters (arrays or values), its generics,
//! its return type, and which type parameter (if any) is the `Real` scalar.

use proc_macro2::TokenStream;
use quote::ToTokens;
use syn::spanned::Spanned;
use syn::{FnArg, GenericParam, Ident, Pat, ReturnType, Type, TypeParamBound};

use crate::{Errors, Kind};

/// A parameter of a kernel or function.
pub struct Param {
    pub name: Ident,
    pub kind: ParamKind,
}

pub enum ParamKind {
    /// `x: &Array<T>`: `ty` is `Array<T>` as written.
    Array { ty: Type },
    /// A value parameter; `mutable` if declared `mut`.
    Value { ty: Type, mutable: bool },
}

impl Param {
    pub fn is_array(&self) -> bool {
        matches!(self.kind, ParamKind::Array { .. })
    }
    /// The type as the Owned/Args tuples see it: `Array<T>` or the value type.
    pub fn owned_ty(&self) -> &Type {
        match &self.kind {
            ParamKind::Array { ty } | ParamKind::Value { ty, .. } => ty,
        }
    }
}

pub struct Signature {
    pub name: Ident,
    pub vis: syn::Visibility,
    pub generics: syn::Generics,
    pub params: Vec<Param>,
    pub ret: Option<Type>,
    /// The generic parameter bounded by `Real`: float literals become `R::lit(..)`.
    pub real: Option<Ident>,
}

impl Signature {
    pub fn parse(f: &syn::ItemFn, kind: Kind, errors: &mut Errors) -> Signature {
        let sig = &f.sig;
        let what = kind.attr();
        if let Some(c) = &sig.constness {
            errors.push(c.span(), format!("a {what} cannot be `const`"));
        }
        if let Some(a) = &sig.asyncness {
            errors.push(a.span(), format!("a {what} cannot be `async`"));
        }
        if let Some(u) = &sig.unsafety {
            errors.push(u.span(), format!("a {what} cannot be `unsafe`"));
        }
        if let Some(v) = &sig.variadic {
            errors.push(v.span(), format!("a {what} cannot be variadic"));
        }
        let mut params = Vec::new();
        for input in &sig.inputs {
            match input {
                FnArg::Receiver(r) => {
                    errors.push(r.span(), format!("a {what} cannot take `self`"));
                }
                FnArg::Typed(pt) => {
                    let (name, mutable) = match &*pt.pat {
                        Pat::Ident(pi) if pi.by_ref.is_none() && pi.subpat.is_none() => {
                            (pi.ident.clone(), pi.mutability.is_some())
                        }
                        other => {
                            errors.push(other.span(), "parameters must be plain names");
                            continue;
                        }
                    };
                    // After an error the parameter is still recorded (as what it most likely
                    // is), so that its uses in the body do not cascade into more errors.
                    let kind = match &*pt.ty {
                        Type::Reference(r) if is_array_type(&r.elem) => {
                            if r.mutability.is_some() {
                                errors.push(
                                    r.span(),
                                    format!(
                                        "`&mut` parameters are not supported: pass `&Array<T>`; \
                                         kernels write arrays through a shared handle (`{name}[i] = v`)"
                                    ),
                                );
                            }
                            if kind == Kind::Func {
                                errors.push(
                                    r.span(),
                                    "a #[diff_func] takes values only; read array elements in \
                                     the kernel and pass them in",
                                );
                            }
                            if mutable {
                                errors.push(pt.pat.span(), "an `&Array` parameter cannot be `mut`");
                            }
                            ParamKind::Array {
                                ty: (*r.elem).clone(),
                            }
                        }
                        Type::Reference(r) => {
                            errors.push(
                                r.span(),
                                "the only reference a kernel takes is `&Array<T>`; pass values \
                                 (scalars, vectors, indices) by value",
                            );
                            ParamKind::Value {
                                ty: (*r.elem).clone(),
                                mutable,
                            }
                        }
                        Type::Ptr(p) => {
                            errors.push(p.span(), "pointers are not supported in kernels");
                            ParamKind::Value {
                                ty: (*p.elem).clone(),
                                mutable,
                            }
                        }
                        Type::ImplTrait(t) => {
                            errors.push(t.span(), "`impl Trait` parameters are not supported; use a generic `R: Real`");
                            ParamKind::Value {
                                ty: pt.ty.as_ref().clone(),
                                mutable,
                            }
                        }
                        ty if is_array_type(ty) => {
                            errors.push(ty.span(), "take arrays by reference: `&Array<T>`");
                            ParamKind::Array { ty: ty.clone() }
                        }
                        ty => ParamKind::Value {
                            ty: ty.clone(),
                            mutable,
                        },
                    };
                    params.push(Param { name, kind });
                }
            }
        }
        let ret = match &sig.output {
            ReturnType::Default => None,
            ReturnType::Type(_, ty) => match &**ty {
                Type::Tuple(t) if t.elems.is_empty() => None,
                ty => Some(ty.clone()),
            },
        };
        if kind == Kind::Kernel {
            if let Some(ty) = &ret {
                errors.push(
                    ty.span(),
                    "a #[diff_kernel] cannot return a value; store results into an `&Array` \
                     parameter (`out[tid()] = v`) or accumulate them (`out.atomic_add(i, v)`)",
                );
            }
        } else if ret.is_none() {
            errors.push(
                sig.ident.span(),
                "a #[diff_func] must return a value (its derivative is taken with respect to it)",
            );
        }
        let mut real = None;
        for gp in &sig.generics.params {
            match gp {
                GenericParam::Type(tp) => {
                    let bounded = tp.bounds.iter().any(is_real_bound)
                        || sig
                            .generics
                            .where_clause
                            .iter()
                            .flat_map(|w| &w.predicates)
                            .any(|p| match p {
                                syn::WherePredicate::Type(pt) => {
                                    tp.ident == pt.bounded_ty.to_token_stream().to_string()
                                        && pt.bounds.iter().any(is_real_bound)
                                }
                                _ => false,
                            });
                    if bounded {
                        if real.is_some() {
                            errors.push(
                                tp.span(),
                                "at most one type parameter may be bounded by `Real` (float \
                                 literals are converted to it)",
                            );
                        }
                        real = Some(tp.ident.clone());
                    }
                }
                GenericParam::Lifetime(l) => {
                    errors.push(l.span(), "lifetime parameters are not supported in kernels");
                }
                GenericParam::Const(_) => {}
            }
        }
        Signature {
            name: sig.ident.clone(),
            vis: f.vis.clone(),
            generics: sig.generics.clone(),
            params,
            ret,
            real,
        }
    }

    pub fn param_index(&self, name: &str) -> Option<usize> {
        self.params.iter().position(|p| p.name == name)
    }

    /// `<R: Real, ...>` of an impl and the matching `where` clause.
    pub fn impl_generics(&self) -> (TokenStream, TokenStream) {
        let (ig, _, wc) = self.generics.split_for_impl();
        (ig.to_token_stream(), wc.to_token_stream())
    }

    /// The generic parameters as a list for an impl header that adds a lifetime first.
    pub fn generic_params(&self) -> Vec<TokenStream> {
        self.generics
            .params
            .iter()
            .map(|p| p.to_token_stream())
            .collect()
    }
}

fn is_real_bound(b: &TypeParamBound) -> bool {
    match b {
        TypeParamBound::Trait(t) => t.path.segments.last().is_some_and(|s| s.ident == "Real"),
        _ => false,
    }
}

fn is_array_type(ty: &Type) -> bool {
    match ty {
        Type::Path(tp) => {
            tp.qself.is_none() && tp.path.segments.last().is_some_and(|s| s.ident == "Array")
        }
        Type::Paren(p) => is_array_type(&p.elem),
        Type::Group(g) => is_array_type(&g.elem),
        _ => false,
    }
}
