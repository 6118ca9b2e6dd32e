//! Expansion: parse -> check -> lower -> emit, and the items of a kernel or a function
//! assembled around the emitted code (or a stub beside the errors).

use proc_macro2::TokenStream;
use quote::{format_ident, quote, ToTokens};
use syn::spanned::Spanned;

use crate::attr::Attr;
use crate::check;
use crate::emit::{self, Emitter};
use crate::ir::Body;
use crate::lanes;
use crate::lower::{ArrayUse, Lowerer};
use crate::signature::{ParamKind, Signature};
use crate::{Errors, Kind};

/// Expands `#[diff_kernel]` or `#[diff_func]` (as `kind` says) on `item`.
pub fn expand(args: TokenStream, item: TokenStream, kind: Kind) -> TokenStream {
    let mut errors = Errors::default();
    let f: syn::ItemFn = match syn::parse2(item) {
        Ok(f) => f,
        Err(e) => {
            let what = kind.attr();
            return syn::Error::new(e.span(), format!("{what} applies to a fn")).to_compile_error();
        }
    };
    let attr = Attr::parse(args, kind, &mut errors);
    let rt = runtime_path(&attr);
    let sig = Signature::parse(&f, kind, &mut errors);
    let passthrough = passthrough_attrs(&f, &mut errors);
    let custom = attr.adjoint.is_some();
    // Lowering assumes a body in the kernel language: it runs only if the check passed.
    let lowered = check::check_body(&f.block, kind, &mut errors)
        .then(|| Lowerer::new(&sig, &rt, kind, &mut errors).lower_body(&f.block));
    let Some((body, uses)) = lowered.filter(|_| errors.is_empty()) else {
        let stub = match kind {
            Kind::Kernel => kernel_stub(&sig, &rt, &passthrough),
            Kind::Func => func_stub(&sig, &rt, &passthrough),
        };
        let errs = errors.to_compile_errors();
        return quote!(#errs #stub);
    };
    let items = match kind {
        Kind::Kernel => kernel_items(&sig, &rt, &body, &uses, &passthrough),
        Kind::Func => {
            let custom = custom.then(|| {
                (
                    attr.adjoint.as_ref().unwrap(),
                    attr.tangent.as_ref().unwrap(),
                    attr.dual_safe,
                )
            });
            func_items(&sig, &rt, &body, custom, &passthrough)
        }
    };
    dump(&sig.name.to_string(), &items);
    items
}

/// Finds the runtime crate as the user's Cargo.toml names it.
fn runtime_path(attr: &Attr) -> TokenStream {
    use proc_macro_crate::{crate_name, FoundCrate};
    if let Some(p) = &attr.krate {
        return p.to_token_stream();
    }
    match crate_name("adflex-runtime") {
        Ok(FoundCrate::Itself) => quote!(::adflex_runtime),
        Ok(FoundCrate::Name(n)) => {
            let id = format_ident!("{}", n);
            quote!(::#id)
        }
        Err(_) => match crate_name("adflex") {
            Ok(FoundCrate::Name(n)) => {
                let id = format_ident!("{}", n);
                quote!(::#id::runtime)
            }
            _ => quote!(::adflex::runtime),
        },
    }
}

/// Attributes copied onto the generated struct (docs, cfg, lints); others are refused.
fn passthrough_attrs(f: &syn::ItemFn, errors: &mut Errors) -> Vec<syn::Attribute> {
    let mut keep = Vec::new();
    for a in &f.attrs {
        let name = a
            .path()
            .get_ident()
            .map(|i| i.to_string())
            .unwrap_or_default();
        match name.as_str() {
            "doc" | "cfg" | "allow" | "warn" | "deny" | "expect" => keep.push(a.clone()),
            _ => errors.push(
                a.span(),
                format!("attribute `#[{name}]` is not supported on a kernel"),
            ),
        }
    }
    keep
}

fn name_lit(sig: &Signature) -> syn::LitStr {
    syn::LitStr::new(&sig.name.to_string(), sig.name.span())
}

fn struct_item(sig: &Signature, attrs: &[syn::Attribute]) -> TokenStream {
    let (name, vis) = (&sig.name, &sig.vis);
    quote! {
        #(#attrs)*
        #[allow(non_camel_case_types)]
        #[derive(Clone, Copy, Debug, Default)]
        #vis struct #name;
    }
}

const LINTS: &str = "unused_mut, unused_variables, unused_assignments, unused_parens, \
    unreachable_code, non_snake_case, clippy::all, clippy::pedantic";

fn lints() -> TokenStream {
    let l: TokenStream = LINTS.parse().unwrap();
    quote!(#[allow(#l)])
}

// ---- kernels ---------------------------------------------------------------------------

fn kernel_items(
    sig: &Signature,
    rt: &TokenStream,
    body: &Body,
    uses: &[ArrayUse],
    attrs: &[syn::Attribute],
) -> TokenStream {
    let name = &sig.name;
    let name_str = name_lit(sig);
    let owned: Vec<_> = sig.params.iter().map(|p| p.owned_ty().clone()).collect();
    let borrowed: Vec<_> = sig
        .params
        .iter()
        .map(|p| match &p.kind {
            ParamKind::Array { ty } => quote!(&'__a #ty),
            ParamKind::Value { ty, .. } => quote!(#ty),
        })
        .collect();
    let idx: Vec<_> = (0..sig.params.len()).map(syn::Index::from).collect();
    let access: Vec<_> = sig
        .params
        .iter()
        .zip(uses)
        .map(|(p, u)| {
            let pname = p.name.to_string();
            let acc = if !p.is_array() {
                quote!(Value)
            } else if u.read.is_some() {
                quote!(Read)
            } else if u.store.is_some() {
                quote!(Store)
            } else if u.atomic.is_some() {
                quote!(Atomic)
            } else {
                quote!(Unused)
            };
            quote!(#rt::kernel::ParamInfo { name: #pname, access: #rt::kernel::Access::#acc })
        })
        .collect();
    let arrays: Vec<_> = sig
        .params
        .iter()
        .zip(&idx)
        .map(|(p, i)| {
            if p.is_array() {
                quote!(::std::option::Option::Some(&__args.#i as &dyn #rt::AnyArray))
            } else {
                quote!(::std::option::Option::None)
            }
        })
        .collect();
    let generic_params = sig.generic_params();
    let (impl_generics, where_clause) = sig.impl_generics();
    let em = Emitter::new(rt, body);
    let run = by_mode(rt, MODES.map(|m| kernel_mode(sig, rt, body, uses, &em, m)));
    let statics = MODES.map(|m| static_scatters(sig, rt, body, uses, &em, m));
    let infos = by_mode(
        rt,
        statics.each_ref().map(|s| match &s.0 {
            Some(Statics { targets, deps }) => quote!(::std::option::Option::Some(
                #rt::kernel::StaticScatters { targets: &[#(#targets),*], deps: &[#(#deps),*] }
            )),
            None => quote!(::std::option::Option::None),
        }),
    );
    let scatter_indices = by_mode(rt, statics.map(|s| s.1));
    let strukt = struct_item(sig, attrs);
    let lints = lints();
    quote! {
        #strukt

        impl<'__a, #(#generic_params),*> #rt::kernel::Kernel<(#(#borrowed,)*)> for #name #where_clause {
            type Owned = (#(#owned,)*);
            #[inline]
            fn to_owned(args: &(#(#borrowed,)*)) -> Self::Owned {
                (#(#rt::kernel::LaunchArg::to_owned_arg(&args.#idx),)*)
            }
        }

        // SAFETY: the body makes its views from `__exec` and drops them before it returns, and
        // `scatter_indices` reports the indices the body's static scatters compute (see
        // `KernelBody`'s contract); the macro generates both from one analysis.
        unsafe impl #impl_generics #rt::kernel::KernelBody<(#(#owned,)*)> for #name #where_clause {
            const NAME: &'static str = #name_str;
            const PARAMS: &'static [#rt::kernel::ParamInfo] = &[#(#access),*];
            fn arrays(__args: &(#(#owned,)*)) -> ::std::vec::Vec<::std::option::Option<&dyn #rt::AnyArray>> {
                ::std::vec![#(#arrays),*]
            }
            #lints
            fn run(
                &self,
                __mode: #rt::kernel::Mode,
                __args: &(#(#owned,)*),
                __range: ::std::ops::Range<usize>,
                __exec: &#rt::kernel::Exec,
            ) -> ::std::vec::Vec<#rt::kernel::ScatterLog> {
                #run
            }
            fn static_scatters(
                __mode: #rt::kernel::Mode,
            ) -> ::std::option::Option<#rt::kernel::StaticScatters> {
                #infos
            }
            #lints
            fn scatter_indices(
                &self,
                __mode: #rt::kernel::Mode,
                __args: &(#(#owned,)*),
                __range: ::std::ops::Range<usize>,
                __exec: &#rt::kernel::Exec,
                __sink: &mut dyn ::std::ops::FnMut(usize, usize, i128),
            ) {
                #scatter_indices
            }
        }
    }
}

/// The three modes, in the order [`by_mode`] takes their code.
const MODES: [Mode; 3] = [Mode::Forward, Mode::Adjoint, Mode::Tangent];

/// `match __mode { .. }` choosing the code of each of [`MODES`].
fn by_mode(rt: &TokenStream, [fwd, adj, tan]: [TokenStream; 3]) -> TokenStream {
    quote! {
        match __mode {
            #rt::kernel::Mode::Forward => { #fwd }
            #rt::kernel::Mode::Adjoint => { #adj }
            #rt::kernel::Mode::Tangent => { #tan }
        }
    }
}

/// The scatters of `mode` other than those at the thread id (which write directly anyway),
/// if every one has static indices (see [`Body::static_indices`]): their parameters and the
/// array parameters their indices read; and the code that reports them thread by thread
/// (`__sink(slot, tid, index)`, `slot` the place of the parameter in the first list).
fn static_scatters(
    sig: &Signature,
    rt: &TokenStream,
    body: &Body,
    uses: &[ArrayUse],
    em: &Emitter,
    mode: Mode,
) -> (Option<Statics>, TokenStream) {
    let kname = sig.name.to_string();
    let at_tid = body.at_tid(sig.params.len());
    let si = body.static_indices(sig.params.len());
    let mut targets = Vec::new();
    let mut roots = Vec::new();
    for (p, (param, u)) in sig.params.iter().zip(uses).enumerate() {
        if !param.is_array() {
            continue;
        }
        // The same choice of view as `kernel_mode`: a read parameter is scattered into (its
        // gradient) in the adjoint; an atomic one in the forward and tangent.
        let indices = match mode {
            Mode::Adjoint if u.read.is_some() && !at_tid.reads[p] => &si.reads[p],
            Mode::Forward | Mode::Tangent
                if u.read.is_none()
                    && u.store.is_none()
                    && u.atomic.is_some()
                    && !at_tid.atomics[p] =>
            {
                &si.atomics[p]
            }
            _ => continue,
        };
        let Some(ix) = indices else {
            return (None, quote!(::std::unreachable!()));
        };
        roots.push((targets.len(), ix.clone()));
        targets.push(p);
    }
    let all: Vec<_> = roots
        .iter()
        .flat_map(|(_, ix)| ix.iter().copied())
        .collect();
    let (lets, deps) = si.closure(&all);
    let mut views = TokenStream::new();
    for &q in &deps {
        let i = syn::Index::from(q);
        let pname = sig.params[q].name.to_string();
        let vw = emit::view(q);
        let site = quote!(&#rt::kernel::Site { kernel: #kname, param: #pname });
        views.extend(quote!(let #vw = #rt::kernel::reader(&__args.#i, __exec, #site);));
    }
    let code = em.lets(&lets);
    let t = em.tid();
    let t = &t;
    let em = &em;
    let sinks = roots.iter().flat_map(|(slot, ix)| {
        ix.iter().map(move |x| {
            let x = em.names(*x).0;
            quote!(__sink(#slot, #t, #rt::kernel::ToIndex::to_i128(#x));)
        })
    });
    let code = quote! {
        #views
        for #t in __range {
            #code
            #(#sinks)*
        }
    };
    (Some(Statics { targets, deps }), code)
}

/// The parameters a mode's static scatters go to and the array parameters their indices read.
struct Statics {
    targets: Vec<usize>,
    deps: Vec<usize>,
}

#[derive(Clone, Copy, PartialEq)]
enum Mode {
    Forward,
    Adjoint,
    Tangent,
}

fn kernel_mode(
    sig: &Signature,
    rt: &TokenStream,
    body: &Body,
    uses: &[ArrayUse],
    em: &Emitter,
    mode: Mode,
) -> TokenStream {
    let kname = sig.name.to_string();
    let at_tid = body.at_tid(sig.params.len());
    let mut views = TokenStream::new();
    let mut finish = Vec::new();
    let mut scatters = Vec::new();
    for (p, (param, u)) in sig.params.iter().zip(uses).enumerate() {
        if !param.is_array() {
            continue;
        }
        let i = syn::Index::from(p);
        let pname = param.name.to_string();
        let site = quote!(&#rt::kernel::Site { kernel: #kname, param: #pname });
        let (vw, gv, tv) = (emit::view(p), emit::grad_view(p), emit::tangent_view(p));
        let arr = quote!(&__args.#i);
        let k = quote!(#rt::kernel);
        if u.read.is_some() {
            views.extend(quote!(let #vw = #k::reader(#arr, __exec, #site);));
            match mode {
                Mode::Adjoint => {
                    let own = at_tid.reads[p];
                    views.extend(
                        quote!(let mut #gv = #k::grad_scatter::<_, #own>(#arr, __exec, #site);),
                    );
                    finish.push(quote!(#gv.finish()));
                    scatters.push(gv);
                }
                Mode::Tangent => {
                    views.extend(quote!(let #tv = #k::tangent_reader(#arr, __exec, #site);))
                }
                Mode::Forward => {}
            }
        } else if u.store.is_some() {
            let distinct = at_tid.stores[p];
            views.extend(match mode {
                Mode::Forward => quote!(let #vw = #k::writer(#arr, __exec, #site, #distinct);),
                Mode::Adjoint => quote!(let #gv = #k::grad_taker(#arr, __exec, #site, #distinct);),
                Mode::Tangent => {
                    quote!(let #tv = #k::tangent_writer(#arr, __exec, #site, #distinct);)
                }
            });
        } else if u.atomic.is_some() {
            let own = at_tid.atomics[p];
            match mode {
                Mode::Forward => {
                    views
                        .extend(quote!(let mut #vw = #k::scatter::<_, #own>(#arr, __exec, #site);));
                    finish.push(quote!(#vw.finish()));
                    scatters.push(vw);
                }
                Mode::Adjoint => {
                    views.extend(quote!(let #gv = #k::grad_reader(#arr, __exec, #site);))
                }
                Mode::Tangent => {
                    views.extend(
                        quote!(let mut #tv = #k::tangent_scatter::<_, #own>(#arr, __exec, #site);),
                    );
                    finish.push(quote!(#tv.finish()));
                    scatters.push(tv);
                }
            }
        }
    }
    // The parameters' values (and their adjoints or tangents) as the thread id of `em` names
    // them.
    let prologue = |em: &Emitter| {
        let mut prologue = TokenStream::new();
        for (p, val) in body.params.iter().enumerate() {
            let Some(val) = *val else { continue }; // an array: read through its view
            let i = syn::Index::from(p);
            let (x, ax, dx) = em.names(val);
            prologue.extend(quote!(let #x = __args.#i;));
            match mode {
                Mode::Adjoint => prologue.extend(quote!(let mut #ax = #rt::zero_like(&#x);)),
                Mode::Tangent => prologue.extend(quote!(let #dx = #rt::zero_like(&#x);)),
                Mode::Forward => {}
            }
        }
        prologue
    };
    // The adjoint's direct loop runs two ids per iteration where the kernel qualifies: the
    // adjoint emitted once per id, zipped.
    let mut pairs = TokenStream::new();
    let code = match mode {
        Mode::Forward => em.forward(&body.block),
        Mode::Adjoint => {
            if lanes::qualifies(&body.block, &|p| at_tid.stores[p]) {
                let [e0, e1] = lanes::emitters(em);
                let (t0, t1) = (e0.tid(), e1.tid());
                let (p0, p1) = (prologue(&e0), prologue(&e1));
                let (c0, c1) = (
                    e0.adjoint_pieces(&body.block, &[]),
                    e1.adjoint_pieces(&body.block, &[]),
                );
                let two = lanes::interleaved([&p0, &p1], [&c0, &c1]);
                pairs = quote! {
                    while __tids.len() >= 2 {
                        let #t0 = __tids.start;
                        let #t1 = #t0 + 1;
                        __tids.start += 2;
                        #two
                    }
                };
            }
            em.adjoint(&body.block, &[])
        }
        Mode::Tangent => em.tangent(&body.block),
    };
    let prologue = prologue(em);
    let t = em.tid();
    let body = quote!(#prologue #code);
    if scatters.is_empty() {
        return quote! {
            #views
            for #t in __range {
                #body
            }
            ::std::vec![#(#finish),*]
        };
    }
    // Thread by thread while a scatter logs; once all write directly (from the start on a
    // serial or in-turn chunk, or after a logged chunk's turn came), the rest of the chunk
    // runs in a loop over direct views (shadowing the scatters' names) without a log path.
    quote! {
        #views
        let mut __tids = __range;
        loop {
            if let (#(::std::option::Option::Some(mut #scatters),)*) = (#(#scatters.direct(),)*) {
                #pairs
                for #t in __tids {
                    #body
                }
                break;
            }
            let ::std::option::Option::Some(#t) = __tids.next() else { break };
            #body
        }
        ::std::vec![#(#finish),*]
    }
}

fn kernel_stub(sig: &Signature, rt: &TokenStream, attrs: &[syn::Attribute]) -> TokenStream {
    let name = &sig.name;
    let name_str = name_lit(sig);
    let strukt = struct_item(sig, attrs);
    quote! {
        #strukt
        impl<__A> #rt::kernel::Kernel<__A> for #name {
            type Owned = ();
            fn to_owned(_: &__A) {}
        }
        // SAFETY: makes no views (never runs).
        unsafe impl #rt::kernel::KernelBody<()> for #name {
            const NAME: &'static str = #name_str;
            const PARAMS: &'static [#rt::kernel::ParamInfo] = &[];
            fn arrays(_: &()) -> ::std::vec::Vec<::std::option::Option<&dyn #rt::AnyArray>> {
                ::std::vec::Vec::new()
            }
            fn run(&self, _: #rt::kernel::Mode, _: &(), _: ::std::ops::Range<usize>, _: &#rt::kernel::Exec) -> ::std::vec::Vec<#rt::kernel::ScatterLog> {
                ::std::unreachable!()
            }
        }
    }
}

// ---- functions -------------------------------------------------------------------------

fn func_items(
    sig: &Signature,
    rt: &TokenStream,
    body: &Body,
    custom: Option<(&syn::Path, &syn::Path, bool)>,
    attrs: &[syn::Attribute],
) -> TokenStream {
    let name = &sig.name;
    let vis = &sig.vis;
    let tys: Vec<_> = sig.params.iter().map(|p| p.owned_ty().clone()).collect();
    let pnames: Vec<_> = sig.params.iter().map(|p| p.name.clone()).collect();
    let ret = sig.ret.as_ref().unwrap();
    let (impl_generics, where_clause) = sig.impl_generics();
    let generics = &sig.generics;
    let em = Emitter::new(rt, body);
    let strukt = struct_item(sig, attrs);
    let lints = lints();
    let args_ty = quote!((#(#tys,)*));
    // A function's parameters are all values (the signature refuses arrays).
    let vals: Vec<_> = body.params.iter().flatten().map(|&p| em.names(p)).collect();
    let xs: Vec<_> = vals.iter().map(|n| n.0.clone()).collect();
    let axs: Vec<_> = vals.iter().map(|n| n.1.clone()).collect();
    let dxs: Vec<_> = vals.iter().map(|n| n.2.clone()).collect();
    let r = body.ret.unwrap();
    let (rv, _, rd) = em.names(r);
    // A custom adjoint may compute in `f64` and drop a `Dual`'s derivative part: refused in
    // `Dual` unless declared safe.
    let dual_safe = !matches!(custom, Some((_, _, false)));
    let (adjoint, tangent) = match custom {
        Some((adj, tan, _)) => (
            quote! {
                let (#(#xs,)*) = __args;
                #adj(#(#xs,)* __adj_out)
            },
            quote! {
                let (#(#xs,)*) = __args;
                let (#(#dxs,)*) = __dots;
                (<Self as #rt::DiffFunc<#args_ty, #ret>>::forward(self, __args), #tan(#(#xs,)* #(#dxs),*))
            },
        ),
        None => {
            let adj_body = em.adjoint(&body.block, &[(r, quote!(__adj_out))]);
            let tan_body = em.tangent(&body.block);
            (
                quote! {
                    let (#(#xs,)*) = __args;
                    #(let mut #axs = #rt::zero_like(&#xs);)*
                    #adj_body
                    (#(#axs,)*)
                },
                quote! {
                    let (#(#xs,)*) = __args;
                    let (#(#dxs,)*) = __dots;
                    #tan_body
                    (#rv, #rd)
                },
            )
        }
    };
    let fwd_body = em.forward(&body.block);
    let doc = format!("Calls `{name}` (the forward function; kernels call it as `{name}(..)`).");
    quote! {
        #strukt

        impl #name {
            #[doc = #doc]
            // The user's own arity: clippy would otherwise flag a generated item the user
            // cannot annotate.
            #[allow(clippy::too_many_arguments)]
            #[inline]
            #vis fn call #generics (#(#pnames: #tys),*) -> #ret #where_clause {
                <Self as #rt::DiffFunc<#args_ty, #ret>>::forward(&#name, (#(#pnames,)*))
            }
        }

        impl #impl_generics #rt::DiffFunc<#args_ty, #ret> for #name #where_clause {
            const DUAL_SAFE: bool = #dual_safe;
            #lints
            #[inline]
            fn forward(&self, __args: #args_ty) -> #ret {
                let (#(#xs,)*) = __args;
                #fwd_body
                #rv
            }
            #lints
            // Always inlined (as Warp's device functions are): the adjoint of a kernel calls
            // it once per thread, and out of line its arguments and results go through
            // memory (the ground contact's adjoint spent 5% of a cloth step in the call).
            #[inline(always)]
            fn adjoint(&self, __args: #args_ty, __adj_out: #ret) -> #args_ty {
                #adjoint
            }
            #lints
            #[inline]
            fn tangent(&self, __args: #args_ty, __dots: #args_ty) -> (#ret, #ret) {
                #tangent
            }
        }
    }
}

fn func_stub(sig: &Signature, rt: &TokenStream, attrs: &[syn::Attribute]) -> TokenStream {
    let name = &sig.name;
    let strukt = struct_item(sig, attrs);
    quote! {
        #strukt
        impl<__A, __O> #rt::DiffFunc<__A, __O> for #name {
            fn forward(&self, _: __A) -> __O { ::std::unreachable!() }
            fn adjoint(&self, _: __A, _: __O) -> __A { ::std::unreachable!() }
            fn tangent(&self, _: __A, _: __A) -> (__O, __O) { ::std::unreachable!() }
        }
    }
}

/// With `ADFLEX_EXPAND_DIR=dir`, writes the generated code of each kernel and function to
/// `dir/<name>.rs`, formatted, so that gradients can be debugged by reading it.
fn dump(name: &str, items: &TokenStream) {
    let Some(dir) = std::env::var_os("ADFLEX_EXPAND_DIR") else {
        return;
    };
    let text = match syn::parse2::<syn::File>(items.clone()) {
        Ok(file) => prettyplease::unparse(&file),
        Err(_) => items.to_string(),
    };
    let dir = std::path::PathBuf::from(dir);
    let _ = std::fs::create_dir_all(&dir);
    let _ = std::fs::write(dir.join(format!("{name}.rs")), text);
}
