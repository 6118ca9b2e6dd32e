//! Syntactic queries on syn trees, shared by [`crate::check`] and [`crate::lower`]: which
//! statements may leave a block or a loop, component names, catch-all patterns, literals.

use quote::ToTokens;
use syn::visit::Visit;
use syn::{BinOp, Expr, Lit, Pat};

/// Whether `op` is a compound assignment (`+=`, `-=`, .., `>>=`).
pub fn is_compound_assign(op: &BinOp) -> bool {
    matches!(
        op,
        BinOp::AddAssign(_)
            | BinOp::SubAssign(_)
            | BinOp::MulAssign(_)
            | BinOp::DivAssign(_)
            | BinOp::RemAssign(_)
            | BinOp::BitAndAssign(_)
            | BinOp::BitOrAssign(_)
            | BinOp::BitXorAssign(_)
            | BinOp::ShlAssign(_)
            | BinOp::ShrAssign(_)
    )
}

/// The component a member names: `.x`, `.y`, `.z`, `.w` are 0 to 3.
pub fn component_index(m: &syn::Member) -> Option<usize> {
    match m {
        syn::Member::Named(id) => match id.to_string().as_str() {
            "x" => Some(0),
            "y" => Some(1),
            "z" => Some(2),
            "w" => Some(3),
            _ => None,
        },
        syn::Member::Unnamed(_) => None,
    }
}

/// Whether a `match` pattern matches everything: `_` or a name.
pub fn is_catch_all(p: &Pat) -> bool {
    matches!(p, Pat::Wild(_)) || matches!(p, Pat::Ident(pi) if pi.subpat.is_none())
}

/// The value of an integer literal (in parentheses or not).
pub fn int_literal(e: &Expr) -> Option<u64> {
    match e {
        Expr::Lit(syn::ExprLit {
            lit: Lit::Int(i), ..
        }) => i.base10_parse().ok(),
        Expr::Paren(p) => int_literal(&p.expr),
        Expr::Group(g) => int_literal(&g.expr),
        _ => None,
    }
}

/// The error for a macro call in a kernel.
pub fn macro_message(m: &syn::Macro) -> String {
    let name = m.path.to_token_stream().to_string();
    format!(
        "macro calls are not supported in kernels (`{name}!`): kernels are compiled to adjoint \
         and tangent code, which a macro would escape"
    )
}

/// Whether `stmt` may leave its block early: a `return` anywhere, or a `break`/`continue`
/// that is not inside a loop of its own.
pub fn may_exit(stmt: &syn::Stmt) -> bool {
    let mut v = Exits {
        depth: 0,
        found: false,
        returns: true,
    };
    v.visit_stmt(stmt);
    v.found
}

/// Whether a loop body can end its loop: a `break` for this loop or a `return`.
pub fn exits_loop(body: &syn::Block) -> bool {
    let mut v = Exits {
        depth: 0,
        found: false,
        returns: true,
    };
    v.visit_block(body);
    v.found
}

/// Whether `body` has a `return` anywhere.
pub fn contains_return(body: &syn::Block) -> bool {
    let mut v = Returns(false);
    v.visit_block(body);
    v.0
}

struct Exits {
    depth: usize,
    found: bool,
    returns: bool,
}

impl<'ast> Visit<'ast> for Exits {
    fn visit_expr_break(&mut self, _: &'ast syn::ExprBreak) {
        if self.depth == 0 {
            self.found = true;
        }
    }
    fn visit_expr_continue(&mut self, _: &'ast syn::ExprContinue) {
        if self.depth == 0 {
            self.found = true;
        }
    }
    fn visit_expr_return(&mut self, _: &'ast syn::ExprReturn) {
        if self.returns {
            self.found = true;
        }
    }
    fn visit_expr_for_loop(&mut self, f: &'ast syn::ExprForLoop) {
        self.depth += 1;
        syn::visit::visit_expr_for_loop(self, f);
        self.depth -= 1;
    }
    fn visit_expr_while(&mut self, f: &'ast syn::ExprWhile) {
        self.depth += 1;
        syn::visit::visit_expr_while(self, f);
        self.depth -= 1;
    }
    fn visit_expr_loop(&mut self, f: &'ast syn::ExprLoop) {
        self.depth += 1;
        syn::visit::visit_expr_loop(self, f);
        self.depth -= 1;
    }
    fn visit_expr_closure(&mut self, _: &'ast syn::ExprClosure) {}
}

struct Returns(bool);
impl<'ast> Visit<'ast> for Returns {
    fn visit_expr_return(&mut self, _: &'ast syn::ExprReturn) {
        self.0 = true;
    }
    fn visit_expr_closure(&mut self, _: &'ast syn::ExprClosure) {}
}

/// Whether a branch of this `if` (or block) ends by leaving: `continue`, `break`, `return`.
pub fn diverges(e: &Expr) -> bool {
    fn block_leaves(b: &syn::Block) -> bool {
        match b.stmts.last() {
            Some(syn::Stmt::Expr(e, _)) => {
                matches!(e, Expr::Continue(_) | Expr::Break(_) | Expr::Return(_)) || diverges(e)
            }
            _ => false,
        }
    }
    match e {
        Expr::If(i) => {
            block_leaves(&i.then_branch)
                || i.else_branch.as_ref().is_some_and(|(_, e)| {
                    diverges(e) || matches!(&**e, Expr::Block(b) if block_leaves(&b.block))
                })
        }
        Expr::Block(b) => block_leaves(&b.block),
        Expr::Paren(p) => diverges(&p.expr),
        _ => false,
    }
}
