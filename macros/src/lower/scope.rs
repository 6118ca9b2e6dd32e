//! The environment of lowering: a stack of scopes binding [`Name`]s (locals, value
//! parameters, the control flags of `break`/`continue`/`return`, and a func's pending return
//! value) to the SSA value they hold now.

use std::collections::HashSet;

use syn::visit::Visit;
use syn::Expr;

use super::Lowerer;
use crate::ir::ValueId;
use crate::syntax::is_compound_assign;

/// A control flag: set by `break`, `continue` or `return`, it guards what follows.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
pub(super) enum Flag {
    Break,
    Continue,
    Return,
}

/// What a binding binds: a local (or value parameter) by its name, a control flag, or the value
/// a `return` has set (funcs).
#[derive(Clone, PartialEq, Eq, Hash, Debug)]
pub(super) enum Name {
    Var(String),
    Flag(Flag),
    ReturnValue,
}

impl From<&str> for Name {
    fn from(s: &str) -> Name {
        Name::Var(s.to_string())
    }
}
impl From<&String> for Name {
    fn from(s: &String) -> Name {
        Name::Var(s.clone())
    }
}
impl From<Flag> for Name {
    fn from(f: Flag) -> Name {
        Name::Flag(f)
    }
}

#[derive(Clone)]
pub(super) struct Binding {
    pub name: Name,
    pub value: ValueId,
    pub mutable: bool,
}

impl Lowerer<'_> {
    pub(super) fn bind(&mut self, name: impl Into<Name>, value: ValueId, mutable: bool) {
        self.env.last_mut().unwrap().push(Binding {
            name: name.into(),
            value,
            mutable,
        });
    }

    pub(super) fn lookup(&self, name: impl Into<Name>) -> Option<&Binding> {
        let name = name.into();
        self.env
            .iter()
            .rev()
            .flat_map(|s| s.iter().rev())
            .find(|b| b.name == name)
    }

    pub(super) fn lookup_mut(&mut self, name: impl Into<Name>) -> Option<&mut Binding> {
        let name = name.into();
        self.env
            .iter_mut()
            .rev()
            .flat_map(|s| s.iter_mut().rev())
            .find(|b| b.name == name)
    }

    pub(super) fn assign(&mut self, name: impl Into<Name>, value: ValueId) {
        self.lookup_mut(name).expect("assign to a bound name").value = value;
    }

    /// Runs `f` in a new innermost scope.
    pub(super) fn scoped<T>(&mut self, f: impl FnOnce(&mut Self) -> T) -> T {
        self.env.push(Vec::new());
        let r = f(self);
        self.env.pop();
        r
    }

    /// The index of the array parameter `e` names, unless a local shadows it.
    pub(super) fn array_param(&self, e: &Expr) -> Option<usize> {
        let Expr::Path(p) = e else { return None };
        let id = p.path.get_ident()?;
        if self.lookup(&id.to_string()).is_some() {
            return None; // shadowed by a local
        }
        let i = self.sig.param_index(&id.to_string())?;
        self.sig.params[i].is_array().then_some(i)
    }
}

/// Names a loop body assigns (its carried values); the return flag and value if it returns.
pub(super) fn assigned_names(body: &syn::Block) -> HashSet<Name> {
    let mut v = Assigned::default();
    v.visit_block(body);
    v.names
}

#[derive(Default)]
pub(super) struct Assigned {
    pub names: HashSet<Name>,
}

impl Assigned {
    fn root(&mut self, e: &Expr) {
        match e {
            Expr::Path(p) => {
                if let Some(id) = p.path.get_ident() {
                    self.names.insert(Name::Var(id.to_string()));
                }
            }
            Expr::Field(f) => self.root(&f.base),
            Expr::Index(i) => self.root(&i.expr),
            Expr::Paren(p) => self.root(&p.expr),
            _ => {}
        }
    }
}

impl<'ast> Visit<'ast> for Assigned {
    fn visit_expr_assign(&mut self, a: &'ast syn::ExprAssign) {
        self.root(&a.left);
        syn::visit::visit_expr_assign(self, a);
    }
    fn visit_expr_binary(&mut self, b: &'ast syn::ExprBinary) {
        if is_compound_assign(&b.op) {
            self.root(&b.left);
        }
        syn::visit::visit_expr_binary(self, b);
    }
    fn visit_expr_return(&mut self, r: &'ast syn::ExprReturn) {
        self.names.insert(Name::Flag(Flag::Return));
        self.names.insert(Name::ReturnValue);
        syn::visit::visit_expr_return(self, r);
    }
    fn visit_expr_closure(&mut self, _: &'ast syn::ExprClosure) {}
}
