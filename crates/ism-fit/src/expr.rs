//! Implicit functions `g: Rⁿ → R`: the [`ImplicitFunction`] trait and user expressions.
//!
//! An [`Expression`] is parsed by `exmex` (variables `x`, `y`, `z`), evaluated in `f64`, its
//! gradient comes from `exmex`'s exact symbolic partial derivatives, and both the value and the
//! gradient are also compiled over [`Interval`] for the Plantinga–Vegter test.
//!
//! The text is read by this module's own parser with the conventional precedence of mathematics,
//! Python and Julia (see [`GRAMMAR`]), then handed to `exmex` fully parenthesized: `exmex` alone
//! lets unary minus bind tighter than `^` (`-x^2` would be `(-x)^2`) and has no exponent notation
//! (`1e-3`).

use std::collections::HashMap;

use exmex::prelude::*;
use exmex::{BinOp, FlatEx, MakeOperators, Operator};

use crate::interval::Interval;
use crate::FitError;

/// Names of the coordinates, in order.
pub const VARIABLES: [&str; 3] = ["x", "y", "z"];

/// The expression grammar, as the CLI's help shows it.
pub const GRAMMAR: &str = "  expr    = term   { (\"+\" | \"-\") term }            left to right
  term    = unary  { (\"*\" | \"/\") unary }            left to right
  unary   = (\"-\" | \"+\") unary | power
  power   = atom [ (\"^\" | \"**\") unary ]             right to left: 2^3^2 = 2^9
  atom    = number | x | y | z | constant | function \"(\" expr \")\" | \"(\" expr \")\"
  number  = digits [\".\" digits] [(\"e\" | \"E\") [\"+\" | \"-\"] digits], e.g. 0.28, .5, 1e-3
  constant: PI π E e TAU τ
  function: sqrt cbrt exp ln log log2 log10 sin cos tan asin acos atan sinh cosh tanh asinh acosh atanh
So -x^2 = -(x^2), 2^-x = 2^(-x), a/b*c = (a/b)*c, as in mathematics, Python and Julia.";

/// Functions of one argument the grammar accepts (those `exmex` can differentiate).
const FUNCTIONS: &[&str] = &[
    "sqrt", "cbrt", "exp", "ln", "log", "log2", "log10", "sin", "cos", "tan", "asin", "acos",
    "atan", "sinh", "cosh", "tanh", "asinh", "acosh", "atanh",
];

/// Named constants.
const CONSTANTS: &[&str] = &["PI", "π", "E", "e", "TAU", "τ"];

/// A parsed expression tree.
#[derive(Clone, Debug, PartialEq)]
enum Node {
    Number(f64),
    /// A variable or a named constant.
    Name(String),
    Negate(Box<Node>),
    Binary(char, Box<Node>, Box<Node>),
    Call(String, Box<Node>),
}

impl Node {
    /// The tree as `exmex` text with every operation parenthesized, so `exmex`'s own priorities
    /// never decide anything. Numbers are written by `f64`'s `Display`: the shortest decimal that
    /// reads back to the same double, never in exponent notation (which `exmex` lacks).
    fn to_exmex(&self, out: &mut String) {
        match self {
            Node::Number(v) => out.push_str(&format!("{v}")),
            Node::Name(n) => out.push_str(n),
            Node::Negate(a) => {
                out.push_str("(-(");
                a.to_exmex(out);
                out.push_str("))");
            }
            Node::Binary(op, a, b) => {
                out.push_str("((");
                a.to_exmex(out);
                out.push(')');
                out.push(*op);
                out.push('(');
                b.to_exmex(out);
                out.push_str("))");
            }
            Node::Call(f, a) => {
                out.push_str(f);
                out.push('(');
                a.to_exmex(out);
                out.push(')');
            }
        }
    }
}

#[derive(Clone, Debug, PartialEq)]
enum Token {
    Number(f64),
    Name(String),
    /// One of `+ - * / ^` (`**` is read as `^`).
    Op(char),
    Open,
    Close,
}

impl Token {
    fn describe(&self) -> String {
        match self {
            Token::Number(v) => format!("the number {v}"),
            Token::Name(n) => format!("`{n}`"),
            Token::Op(c) => format!("`{c}`"),
            Token::Open => "`(`".to_string(),
            Token::Close => "`)`".to_string(),
        }
    }
}

/// Splits `text` into tokens with their character positions (1-based, for messages).
fn tokenize(text: &str) -> Result<Vec<(Token, usize)>, String> {
    let chars: Vec<char> = text.chars().collect();
    let mut tokens = Vec::new();
    let mut i = 0;
    let is_name_start = |c: char| c.is_alphabetic() || c == '_';
    while i < chars.len() {
        let c = chars[i];
        let start = i;
        if c.is_whitespace() {
            i += 1;
            continue;
        }
        if c.is_ascii_digit() || (c == '.' && chars.get(i + 1).is_some_and(|d| d.is_ascii_digit()))
        {
            while i < chars.len() && chars[i].is_ascii_digit() {
                i += 1;
            }
            if i < chars.len() && chars[i] == '.' {
                i += 1;
                while i < chars.len() && chars[i].is_ascii_digit() {
                    i += 1;
                }
            }
            // An exponent only when digits follow: `2e` stays the number 2 and the name `e`.
            if i < chars.len() && (chars[i] == 'e' || chars[i] == 'E') {
                let mut j = i + 1;
                if j < chars.len() && (chars[j] == '+' || chars[j] == '-') {
                    j += 1;
                }
                if j < chars.len() && chars[j].is_ascii_digit() {
                    while j < chars.len() && chars[j].is_ascii_digit() {
                        j += 1;
                    }
                    i = j;
                }
            }
            let literal: String = chars[start..i].iter().collect();
            let value: f64 = literal
                .parse()
                .map_err(|_| format!("`{literal}` at character {} is not a number", start + 1))?;
            if !value.is_finite() {
                return Err(format!(
                    "`{literal}` at character {} is too large for a double",
                    start + 1
                ));
            }
            tokens.push((Token::Number(value), start + 1));
        } else if is_name_start(c) {
            while i < chars.len() && (is_name_start(chars[i]) || chars[i].is_ascii_digit()) {
                i += 1;
            }
            tokens.push((Token::Name(chars[start..i].iter().collect()), start + 1));
        } else {
            let token = match c {
                '*' if chars.get(i + 1) == Some(&'*') => {
                    i += 1;
                    Token::Op('^')
                }
                '+' | '-' | '*' | '/' | '^' => Token::Op(c),
                '(' => Token::Open,
                ')' => Token::Close,
                _ => {
                    return Err(format!(
                    "unexpected character `{c}` at character {}; the grammar has + - * / ^ ** ( )",
                    start + 1
                ))
                }
            };
            i += 1;
            tokens.push((token, start + 1));
        }
    }
    Ok(tokens)
}

/// Recursive descent over [`GRAMMAR`].
struct Parser {
    tokens: Vec<(Token, usize)>,
    at: usize,
    /// Characters in the text, for "at the end" messages.
    len: usize,
}

impl Parser {
    fn peek(&self) -> Option<&Token> {
        self.tokens.get(self.at).map(|(t, _)| t)
    }

    fn position(&self) -> String {
        match self.tokens.get(self.at) {
            Some((t, p)) => format!("{} at character {p}", t.describe()),
            None => format!("the end of the expression (character {})", self.len + 1),
        }
    }

    fn expr(&mut self) -> Result<Node, String> {
        let mut left = self.term()?;
        while let Some(Token::Op(op @ ('+' | '-'))) = self.peek() {
            let op = *op;
            self.at += 1;
            let right = self.term()?;
            left = Node::Binary(op, Box::new(left), Box::new(right));
        }
        Ok(left)
    }

    fn term(&mut self) -> Result<Node, String> {
        let mut left = self.unary()?;
        while let Some(Token::Op(op @ ('*' | '/'))) = self.peek() {
            let op = *op;
            self.at += 1;
            let right = self.unary()?;
            left = Node::Binary(op, Box::new(left), Box::new(right));
        }
        Ok(left)
    }

    fn unary(&mut self) -> Result<Node, String> {
        match self.peek() {
            Some(Token::Op('-')) => {
                self.at += 1;
                Ok(Node::Negate(Box::new(self.unary()?)))
            }
            Some(Token::Op('+')) => {
                self.at += 1;
                self.unary()
            }
            _ => self.power(),
        }
    }

    fn power(&mut self) -> Result<Node, String> {
        let base = self.atom()?;
        if let Some(Token::Op('^')) = self.peek() {
            self.at += 1;
            let exponent = self.unary()?;
            return Ok(Node::Binary('^', Box::new(base), Box::new(exponent)));
        }
        Ok(base)
    }

    fn atom(&mut self) -> Result<Node, String> {
        let expected = "expected a number, a variable, a constant, a function or `(`";
        let after = match self.at.checked_sub(1).and_then(|k| self.tokens.get(k)) {
            Some((t, _)) => format!(" after {}", t.describe()),
            None => String::new(),
        };
        let Some((token, _)) = self.tokens.get(self.at).cloned() else {
            return Err(format!("{expected}{after}, found {}", self.position()));
        };
        match token {
            Token::Number(v) => {
                self.at += 1;
                Ok(Node::Number(v))
            }
            Token::Open => {
                self.at += 1;
                let inner = self.expr()?;
                self.close()?;
                Ok(inner)
            }
            Token::Name(name) => {
                let is_call = matches!(self.tokens.get(self.at + 1), Some((Token::Open, _)));
                if is_call {
                    if !FUNCTIONS.contains(&name.as_str()) {
                        return Err(format!(
                            "unknown function `{name}` at {}; known: {}",
                            self.position(),
                            FUNCTIONS.join(" ")
                        ));
                    }
                    self.at += 2;
                    let argument = self.expr()?;
                    self.close()?;
                    return Ok(Node::Call(name, Box::new(argument)));
                }
                if FUNCTIONS.contains(&name.as_str()) {
                    return Err(format!(
                        "function `{name}` at {} needs its argument in parentheses",
                        self.position()
                    ));
                }
                self.at += 1;
                Ok(Node::Name(name))
            }
            Token::Op(_) | Token::Close => {
                Err(format!("{expected}{after}, found {}", self.position()))
            }
        }
    }

    fn close(&mut self) -> Result<(), String> {
        if let Some(Token::Close) = self.peek() {
            self.at += 1;
            Ok(())
        } else {
            Err(format!("expected `)`, found {}", self.position()))
        }
    }
}

/// Parses `text` by [`GRAMMAR`] into its tree. Names other than functions are passed on;
/// [`Expression::parse`] checks them against the variables.
fn parse_tree(text: &str) -> Result<Node, String> {
    let tokens = tokenize(text)?;
    if tokens.is_empty() {
        return Err("the expression is empty".to_string());
    }
    let mut parser = Parser {
        tokens,
        at: 0,
        len: text.chars().count(),
    };
    let tree = parser.expr()?;
    if parser.at < parser.tokens.len() {
        return Err(format!(
            "expected an operator (+ - * / ^) or the end, found {}",
            parser.position()
        ));
    }
    Ok(tree)
}

/// Functions of one argument, as the tape evaluates them.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Fun {
    Sqrt,
    Cbrt,
    Exp,
    Ln,
    Log2,
    Log10,
    Sin,
    Cos,
    Tan,
    Asin,
    Acos,
    Atan,
    Sinh,
    Cosh,
    Tanh,
    Asinh,
    Acosh,
    Atanh,
}

impl Fun {
    fn of(name: &str) -> Option<Fun> {
        Some(match name {
            "sqrt" => Fun::Sqrt,
            "cbrt" => Fun::Cbrt,
            "exp" => Fun::Exp,
            "ln" | "log" => Fun::Ln,
            "log2" => Fun::Log2,
            "log10" => Fun::Log10,
            "sin" => Fun::Sin,
            "cos" => Fun::Cos,
            "tan" => Fun::Tan,
            "asin" => Fun::Asin,
            "acos" => Fun::Acos,
            "atan" => Fun::Atan,
            "sinh" => Fun::Sinh,
            "cosh" => Fun::Cosh,
            "tanh" => Fun::Tanh,
            "asinh" => Fun::Asinh,
            "acosh" => Fun::Acosh,
            "atanh" => Fun::Atanh,
            _ => return None,
        })
    }

    /// `f(a)`, as `exmex`'s float operators compute it.
    fn apply(self, a: f64) -> f64 {
        match self {
            Fun::Sqrt => a.sqrt(),
            Fun::Cbrt => a.cbrt(),
            Fun::Exp => a.exp(),
            Fun::Ln => a.ln(),
            Fun::Log2 => a.log2(),
            Fun::Log10 => a.log10(),
            Fun::Sin => a.sin(),
            Fun::Cos => a.cos(),
            Fun::Tan => a.tan(),
            Fun::Asin => a.asin(),
            Fun::Acos => a.acos(),
            Fun::Atan => a.atan(),
            Fun::Sinh => a.sinh(),
            Fun::Cosh => a.cosh(),
            Fun::Tanh => a.tanh(),
            Fun::Asinh => a.asinh(),
            Fun::Acosh => a.acosh(),
            Fun::Atanh => a.atanh(),
        }
    }

    /// `f'(a)`, given `v = f(a)`.
    fn derivative(self, a: f64, v: f64) -> f64 {
        match self {
            Fun::Sqrt => 0.5 / v,
            Fun::Cbrt => 1.0 / (3.0 * v * v),
            Fun::Exp => v,
            Fun::Ln => 1.0 / a,
            Fun::Log2 => 1.0 / (a * std::f64::consts::LN_2),
            Fun::Log10 => 1.0 / (a * std::f64::consts::LN_10),
            Fun::Sin => a.cos(),
            Fun::Cos => -a.sin(),
            Fun::Tan => 1.0 + v * v,
            Fun::Asin => 1.0 / (1.0 - a * a).sqrt(),
            Fun::Acos => -1.0 / (1.0 - a * a).sqrt(),
            Fun::Atan => 1.0 / (1.0 + a * a),
            Fun::Sinh => a.cosh(),
            Fun::Cosh => a.sinh(),
            Fun::Tanh => 1.0 - v * v,
            Fun::Asinh => 1.0 / (a * a + 1.0).sqrt(),
            Fun::Acosh => 1.0 / (a * a - 1.0).sqrt(),
            Fun::Atanh => 1.0 / (1.0 - a * a),
        }
    }
}

/// `a^b`: `a·a` for the exponent 2 (the common `x^2`; `powf` costs ~20× a product there and
/// is not always correctly rounded, the product is), `powf` otherwise.
fn power(a: f64, b: f64) -> f64 {
    if b == 2.0 {
        a * a
    } else {
        a.powf(b)
    }
}

/// One instruction of a [`Tape`]; operands are earlier slots.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Ins {
    Const(f64),
    Var(usize),
    Neg(usize),
    Add(usize, usize),
    Sub(usize, usize),
    Mul(usize, usize),
    Div(usize, usize),
    /// `a^c` with a constant exponent `c`.
    PowConst(usize, f64),
    Pow(usize, usize),
    Call(Fun, usize),
}

/// An expression compiled to straight-line code over slots: the value in one pass, the value
/// and gradient (forward-mode differentiation) in one pass, without the allocations and
/// function-pointer dispatch of a general evaluator. Subtrees without variables are folded.
/// Issue 17: `g` and `∇g` through `exmex` were ~45 % of a torus fit at 1e-4 (`perf`), `powf`
/// for `x^2` alone ~25 %.
#[derive(Clone, Debug, PartialEq)]
struct Tape {
    ins: Vec<Ins>,
    /// Which coordinates occur (the others have derivative 0 exactly).
    uses: [bool; 3],
}

/// Slots kept on the stack (a short buffer, a long one); longer tapes use the heap. The
/// torus preset's tape has 22.
/// The longest expression text [`Expression::parse`] takes, in bytes: far beyond any formula
/// written by hand (the tangle cube's is 46 bytes), and short enough to bound what `exmex`'s symbolic
/// derivatives cost, which grows about quadratically with the terms of a sum: a 200-term
/// `x^2+…` (805 bytes) takes 0.7 GB and ~3 CPU-s to fit at 0.1, a 1,000-term one (4,005 bytes)
/// 21 GB and 112 CPU-s (session 24, `ism fit --expr`).
pub const MAX_EXPRESSION_BYTES: usize = 1024;
/// The stack of the thread [`Expression::parse`] runs on: `exmex`'s derivative of a sum recurses
/// once per term at tens of kilobytes a level (a 200-term sum overflowed the main thread's
/// 8 MiB). Address space only: pages are touched as the recursion reaches them.
const PARSE_STACK_BYTES: usize = 256 << 20;

const TAPE_SHORT: usize = 24;
const TAPE_LONG: usize = 96;

impl Tape {
    /// Compiles `node`; `None` for a name that is neither a coordinate of `dim` nor a constant.
    fn compile(node: &Node, dim: usize) -> Option<Tape> {
        let mut tape = Tape {
            ins: Vec::new(),
            uses: [false; 3],
        };
        tape.push(node, dim)?;
        Some(tape.shared())
    }

    /// The same code with each repeated instruction (the same operation on the same slots, or
    /// the same constant bit for bit) computed once: every slot still gets the same operations on
    /// the same numbers, so values and gradients are the same bits. The torus preset writes
    /// `x^2 + y^2` twice: 21 instructions → 16, and its gradient tape was ~16 % of a torus fit at
    /// 2e-4 (`perf`, issue 17, session 22). Sharing after compiling, not while: the constant
    /// folding truncates the code after a subtree's first slot, which must be the subtree's own.
    fn shared(self) -> Tape {
        let last = self.ins.len().saturating_sub(1);
        let mut out = Tape {
            ins: Vec::with_capacity(self.ins.len()),
            uses: self.uses,
        };
        // Old slot → new slot, and each instruction's key → its new slot.
        let mut slot = Vec::with_capacity(self.ins.len());
        let mut seen: HashMap<(u8, usize, usize, u64), usize> = HashMap::new();
        for (i, ins) in self.ins.iter().enumerate() {
            let s = |a: usize| slot[a];
            let ins = match *ins {
                Ins::Const(c) => Ins::Const(c),
                Ins::Var(k) => Ins::Var(k),
                Ins::Neg(a) => Ins::Neg(s(a)),
                Ins::Add(a, b) => Ins::Add(s(a), s(b)),
                Ins::Sub(a, b) => Ins::Sub(s(a), s(b)),
                Ins::Mul(a, b) => Ins::Mul(s(a), s(b)),
                Ins::Div(a, b) => Ins::Div(s(a), s(b)),
                Ins::PowConst(a, c) => Ins::PowConst(s(a), c),
                Ins::Pow(a, b) => Ins::Pow(s(a), s(b)),
                Ins::Call(f, a) => Ins::Call(f, s(a)),
            };
            let key = match ins {
                Ins::Const(c) => (0, 0, 0, c.to_bits()),
                Ins::Var(k) => (1, k, 0, 0),
                Ins::Neg(a) => (2, a, 0, 0),
                Ins::Add(a, b) => (3, a, b, 0),
                Ins::Sub(a, b) => (4, a, b, 0),
                Ins::Mul(a, b) => (5, a, b, 0),
                Ins::Div(a, b) => (6, a, b, 0),
                Ins::PowConst(a, c) => (7, a, 0, c.to_bits()),
                Ins::Pow(a, b) => (8, a, b, 0),
                Ins::Call(f, a) => (9, a, f as usize, 0),
            };
            // The result is read from the last slot: the root is always emitted last.
            match seen.get(&key) {
                Some(&at) if i != last => slot.push(at),
                _ => {
                    seen.insert(key, out.ins.len());
                    slot.push(out.emit(ins));
                }
            }
        }
        out
    }

    fn constant(&self, slot: usize) -> Option<f64> {
        match self.ins[slot] {
            Ins::Const(c) => Some(c),
            _ => None,
        }
    }

    fn emit(&mut self, ins: Ins) -> usize {
        self.ins.push(ins);
        self.ins.len() - 1
    }

    /// Appends `node`'s code and returns its slot.
    fn push(&mut self, node: &Node, dim: usize) -> Option<usize> {
        use std::f64::consts::{E, PI, TAU};
        Some(match node {
            Node::Number(v) => self.emit(Ins::Const(*v)),
            Node::Name(n) => {
                if let Some(k) = VARIABLES[..dim].iter().position(|v| v == n) {
                    self.uses[k] = true;
                    self.emit(Ins::Var(k))
                } else {
                    let c = match n.as_str() {
                        "PI" | "π" => PI,
                        "E" | "e" => E,
                        "TAU" | "τ" => TAU,
                        _ => return None,
                    };
                    self.emit(Ins::Const(c))
                }
            }
            Node::Negate(a) => {
                let a = self.push(a, dim)?;
                match self.constant(a) {
                    Some(c) => self.fold(a, -c),
                    None => self.emit(Ins::Neg(a)),
                }
            }
            Node::Call(f, a) => {
                let f = Fun::of(f)?;
                let a = self.push(a, dim)?;
                match self.constant(a) {
                    Some(c) => self.fold(a, f.apply(c)),
                    None => self.emit(Ins::Call(f, a)),
                }
            }
            Node::Binary(op, a, b) => {
                let a = self.push(a, dim)?;
                let b = self.push(b, dim)?;
                match (self.constant(a), self.constant(b)) {
                    (Some(x), Some(y)) => {
                        let v = match op {
                            '+' => x + y,
                            '-' => x - y,
                            '*' => x * y,
                            '/' => x / y,
                            _ => power(x, y),
                        };
                        self.ins.truncate(a);
                        self.emit(Ins::Const(v))
                    }
                    (_, Some(y)) if *op == '^' => {
                        self.ins.truncate(b);
                        self.emit(Ins::PowConst(a, y))
                    }
                    _ => self.emit(match op {
                        '+' => Ins::Add(a, b),
                        '-' => Ins::Sub(a, b),
                        '*' => Ins::Mul(a, b),
                        '/' => Ins::Div(a, b),
                        _ => Ins::Pow(a, b),
                    }),
                }
            }
        })
    }

    /// Replaces the constant at `slot` (the last code) by `v`.
    fn fold(&mut self, slot: usize, v: f64) -> usize {
        self.ins.truncate(slot);
        self.emit(Ins::Const(v))
    }

    /// `g(p)`.
    fn value(&self, p: &[f64]) -> f64 {
        let n = self.ins.len();
        if n <= TAPE_SHORT {
            self.run_value(p, &mut [0.0; TAPE_SHORT][..n])
        } else if n <= TAPE_LONG {
            self.run_value(p, &mut [0.0; TAPE_LONG][..n])
        } else {
            self.run_value(p, &mut vec![0.0; n])
        }
    }

    fn run_value(&self, p: &[f64], r: &mut [f64]) -> f64 {
        for (i, ins) in self.ins.iter().enumerate() {
            r[i] = match *ins {
                Ins::Const(c) => c,
                Ins::Var(k) => p[k],
                Ins::Neg(a) => -r[a],
                Ins::Add(a, b) => r[a] + r[b],
                Ins::Sub(a, b) => r[a] - r[b],
                Ins::Mul(a, b) => r[a] * r[b],
                Ins::Div(a, b) => r[a] / r[b],
                Ins::PowConst(a, c) => power(r[a], c),
                Ins::Pow(a, b) => power(r[a], r[b]),
                Ins::Call(f, a) => f.apply(r[a]),
            };
        }
        r[r.len() - 1]
    }

    /// `g(p)`, and `∇g(p)` into `gradient` (forward mode).
    fn gradient(&self, p: &[f64], gradient: &mut [f64]) -> f64 {
        const ZERO: (f64, [f64; 3]) = (0.0, [0.0; 3]);
        let n = self.ins.len();
        if n <= TAPE_SHORT {
            self.run_gradient(p, gradient, &mut [ZERO; TAPE_SHORT][..n])
        } else if n <= TAPE_LONG {
            self.run_gradient(p, gradient, &mut [ZERO; TAPE_LONG][..n])
        } else {
            self.run_gradient(p, gradient, &mut vec![ZERO; n])
        }
    }

    /// [`Tape::gradient`] at each point's first `dim` coordinates into `out`, through one work
    /// space: every slot is written before it is read, so it needs no clearing between points.
    fn gradient_each(&self, dim: usize, points: &[[f64; 3]], out: &mut Vec<(f64, [f64; 3])>) {
        const ZERO: (f64, [f64; 3]) = (0.0, [0.0; 3]);
        let n = self.ins.len();
        // On the stack for the short tapes, as in [`Tape::gradient`]: the optimizer calls this
        // once per trial step (5.6 M times in a torus fit at 1e-4).
        let (mut short, mut long);
        let r: &mut [(f64, [f64; 3])] = if n <= TAPE_SHORT {
            short = [ZERO; TAPE_SHORT];
            &mut short[..n]
        } else {
            long = vec![ZERO; n];
            &mut long
        };
        out.clear();
        out.extend(points.iter().map(|p| {
            let mut grad = [0.0; 3];
            let v = self.run_gradient(&p[..dim], &mut grad[..dim], r);
            (v, grad)
        }));
    }

    fn run_gradient(&self, p: &[f64], gradient: &mut [f64], r: &mut [(f64, [f64; 3])]) -> f64 {
        let n = r.len();
        let scale = |d: &[f64; 3], s: f64| [d[0] * s, d[1] * s, d[2] * s];
        for i in 0..n {
            r[i] = match self.ins[i] {
                Ins::Const(c) => (c, [0.0; 3]),
                Ins::Var(k) => {
                    let mut d = [0.0; 3];
                    d[k] = 1.0;
                    (p[k], d)
                }
                Ins::Neg(a) => (-r[a].0, scale(&r[a].1, -1.0)),
                Ins::Add(a, b) => {
                    let ((x, dx), (y, dy)) = (r[a], r[b]);
                    (x + y, [dx[0] + dy[0], dx[1] + dy[1], dx[2] + dy[2]])
                }
                Ins::Sub(a, b) => {
                    let ((x, dx), (y, dy)) = (r[a], r[b]);
                    (x - y, [dx[0] - dy[0], dx[1] - dy[1], dx[2] - dy[2]])
                }
                Ins::Mul(a, b) => {
                    let ((x, dx), (y, dy)) = (r[a], r[b]);
                    (
                        x * y,
                        [
                            dx[0] * y + x * dy[0],
                            dx[1] * y + x * dy[1],
                            dx[2] * y + x * dy[2],
                        ],
                    )
                }
                Ins::Div(a, b) => {
                    let ((x, dx), (y, dy)) = (r[a], r[b]);
                    let q = x / y;
                    (
                        q,
                        [
                            (dx[0] - q * dy[0]) / y,
                            (dx[1] - q * dy[1]) / y,
                            (dx[2] - q * dy[2]) / y,
                        ],
                    )
                }
                Ins::PowConst(a, c) => {
                    let (x, dx) = r[a];
                    let s = if c == 2.0 {
                        2.0 * x
                    } else if c == 1.0 {
                        1.0
                    } else {
                        c * power(x, c - 1.0)
                    };
                    (power(x, c), scale(&dx, s))
                }
                Ins::Pow(a, b) => {
                    let ((x, dx), (y, dy)) = (r[a], r[b]);
                    let v = power(x, y);
                    // d(x^y) = x^y (y' ln x + y x'/x).
                    let (l, q) = (x.ln(), y / x);
                    (
                        v,
                        [
                            v * (dy[0] * l + q * dx[0]),
                            v * (dy[1] * l + q * dx[1]),
                            v * (dy[2] * l + q * dx[2]),
                        ],
                    )
                }
                Ins::Call(f, a) => {
                    let (x, dx) = r[a];
                    let v = f.apply(x);
                    (v, scale(&dx, f.derivative(x, v)))
                }
            };
        }
        let (v, d) = r[n - 1];
        for (k, g) in gradient.iter_mut().enumerate() {
            // A coordinate that does not occur has derivative 0 exactly (not 0·∞ = NaN).
            *g = if self.uses[k] { d[k] } else { 0.0 };
        }
        v
    }
}

/// Interval enclosures of a function and its gradient over a box.
#[derive(Clone, Debug, PartialEq)]
pub struct Enclosure {
    /// Encloses `g` over the box.
    pub value: Interval,
    /// Encloses each partial derivative over the box.
    pub gradient: Vec<Interval>,
}

/// What [`ImplicitFunction::pv_witness`] knows cheaply about a box: the value part of its
/// enclosure and one gradient every box containing it has among its generators.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PvWitness {
    /// [`Enclosure::value`] of [`ImplicitFunction::enclose`] over the box, bit for bit.
    pub value: Interval,
    /// A unit vector (the first `n` components) that, for every box `B` containing the box,
    /// is bit for bit one of the vectors [`ImplicitFunction::gradient_generators`]`(B)` appends
    /// and lies within [`GENERATOR_ERROR`] per component of [`Enclosure::gradient`] of
    /// [`ImplicitFunction::enclose`]`(B)`.
    pub normal: [f64; 3],
    /// Whether [`Enclosure::gradient`] of [`ImplicitFunction::enclose`] over the box is exactly
    /// `[-1, 1]` in every component (a mesh's, wherever the value enclosure excludes 0).
    pub unit_gradient: bool,
}

/// Component-wise error allowed in the unit vectors of
/// [`ImplicitFunction::gradient_generators`]: computed normals (a cross product of differences over
/// its length) are within a few ulps; 10⁻⁹ is generous, as the mesh's own normal margin.
pub const GENERATOR_ERROR: f64 = 1e-9;

/// A function whose zero set is the shape to fit.
pub trait ImplicitFunction: Sync {
    /// Number of variables `n` (2 or 3).
    fn dim(&self) -> usize;
    /// `g(p)`.
    fn value(&self, p: &[f64]) -> f64;
    /// Writes `∇g(p)` into `gradient` and returns `g(p)`.
    fn gradient(&self, p: &[f64], gradient: &mut [f64]) -> f64;
    /// Enclosures of `g` and `∇g` over the box `[lo, hi]`, or `None` when the function has no
    /// interval extension.
    fn enclose(&self, lo: &[f64], hi: &[f64]) -> Option<Enclosure>;

    /// [`ImplicitFunction::gradient`] at each of `points` (the first [`ImplicitFunction::dim`]
    /// coordinates), into `out` (`g` and `∇g`, zero past `dim`): the same numbers, for a batch.
    /// The optimizer asks for its samples this way: an expression then sets up its work space
    /// once per batch instead of once per point.
    fn gradient_each(&self, points: &[[f64; 3]], out: &mut Vec<(f64, [f64; 3])>) {
        let n = self.dim();
        out.clear();
        out.extend(points.iter().map(|p| {
            let mut grad = [0.0; 3];
            let v = self.gradient(&p[..n], &mut grad[..n]);
            (v, grad)
        }));
    }

    /// Appends to `out` unit vectors (`n` numbers each, each component within
    /// [`GENERATOR_ERROR`] of the true vector's) whose conic hull holds `∇g` at every point of
    /// the box `[lo, hi]` where it exists, and returns `true`; returns `false` (and appends
    /// nothing) when the function has none to give. The Plantinga–Vegter test asks for them when
    /// the component-wise [`Enclosure::gradient`] does not decide: two gradients in the hull of
    /// generators whose pairwise dot products are positive have a positive dot product
    /// (bilinearity), while a box of the same vectors loses that once they spread ±35° around an
    /// axis. A mesh's distance gives its nearby triangles' normals.
    fn gradient_generators(&self, _lo: &[f64], _hi: &[f64], _out: &mut Vec<f64>) -> bool {
        false
    }

    /// A cheap [`PvWitness`] for the box `[lo, hi]`, or `None` (the default: the function has
    /// none; also wherever [`ImplicitFunction::enclose`] is `None`). Two witnesses of boxes inside
    /// a cell whose normals point apart (negative dot product) show, without the enclosures'
    /// gradients or the generators, that the Plantinga–Vegter test of the cell fails: both lie in
    /// every gradient enclosure and every generator set those boxes are part of. A mesh's
    /// distance gives the normal of the triangle nearest to the box's centre (one nearest-point
    /// query, where the generators cost 64 and a range query; issue 17, session 23).
    ///
    /// A function that gives witnesses has enclosures wherever it gives one, with no NaN
    /// bound in their gradients (the test skips enclosures that [`PvWitness::unit_gradient`]
    /// already names).
    fn pv_witness(&self, _lo: &[f64], _hi: &[f64]) -> Option<PvWitness> {
        None
    }

    /// Appends unit vectors that hold, bit for bit, every vector
    /// [`ImplicitFunction::gradient_generators`] appends for each of `boxes` (and maybe more),
    /// and returns `true`; `false` (appending nothing) when the function has none to give (the
    /// default). When these agree pairwise so do the boxes' generators: the Plantinga–Vegter
    /// test passes on them without computing them.
    fn gradient_generators_superset(
        &self,
        _boxes: &[(&[f64], &[f64])],
        _out: &mut Vec<f64>,
    ) -> bool {
        false
    }

    /// `|g(p)| / |∇g(p)|`: the first-order estimate of the distance from `p` to the zero set
    /// (infinite where the gradient vanishes).
    fn distance_estimate(&self, p: &[f64]) -> f64 {
        let mut grad = [0.0; 3];
        let n = self.dim();
        let v = self.gradient(p, &mut grad[..n]);
        let norm = grad[..n].iter().map(|g| g * g).sum::<f64>().sqrt();
        if norm > 0.0 {
            v.abs() / norm
        } else if v == 0.0 {
            0.0
        } else {
            f64::INFINITY
        }
    }

    /// A certified upper bound on the distance from `p` to the zero set, searching out to
    /// `reach` (`∞` if nothing is found): by default [`crate::measure::bracket_distance`], which
    /// holds for any continuous `g` whatever its gradient does.
    fn distance_bound(&self, p: &[f64], reach: f64) -> f64 {
        crate::measure::bracket_distance(self, p, reach)
    }

    /// The zero set's triangles, each as its three corners, when it is known explicitly (a
    /// mesh: the measure's certified `Z → S` cover refines them); `None` otherwise (the zero set
    /// is then covered by interval boxes).
    fn surface_triangles(&self) -> Option<Vec<[[f64; 3]; 3]>> {
        None
    }

    /// Whether [`ImplicitFunction::surface_triangles`] gives triangles (the zero set is explicit) and
    /// [`ImplicitFunction::distance_bound`] is the exact distance.
    fn is_explicit(&self) -> bool {
        false
    }
}

/// `exmex` operators over [`Interval`], with the priorities of `exmex`'s float operators so a text
/// parses to the same tree in both number types.
#[derive(Clone, Debug)]
pub struct IntervalOps;

impl MakeOperators<Interval> for IntervalOps {
    fn make<'a>() -> Vec<Operator<'a, Interval>> {
        use std::f64::consts::{E, PI, TAU};
        // Constants that are not exact doubles are widened like literals.
        let around = Interval::around;
        vec![
            Operator::make_bin(
                "^",
                BinOp {
                    apply: |a: Interval, b| a.pow(b),
                    prio: 4,
                    is_commutative: false,
                },
            ),
            Operator::make_bin(
                "*",
                BinOp {
                    apply: |a: Interval, b| a * b,
                    prio: 2,
                    is_commutative: true,
                },
            ),
            Operator::make_bin(
                "/",
                BinOp {
                    apply: |a: Interval, b| a / b,
                    prio: 3,
                    is_commutative: false,
                },
            ),
            Operator::make_bin_unary(
                "+",
                BinOp {
                    apply: |a: Interval, b| a + b,
                    prio: 0,
                    is_commutative: true,
                },
                |a| a,
            ),
            Operator::make_bin_unary(
                "-",
                BinOp {
                    apply: |a: Interval, b| a - b,
                    prio: 1,
                    is_commutative: false,
                },
                |a: Interval| -a,
            ),
            Operator::make_unary("abs", |a: Interval| a.abs()),
            Operator::make_unary("signum", |a: Interval| a.signum()),
            Operator::make_unary("sin", |a: Interval| a.sin()),
            Operator::make_unary("cos", |a: Interval| a.cos()),
            Operator::make_unary("tan", |a: Interval| a.tan()),
            Operator::make_unary("exp", |a: Interval| a.exp()),
            Operator::make_unary("sqrt", |a: Interval| a.sqrt()),
            Operator::make_unary("ln", |a: Interval| a.ln()),
            Operator::make_unary("log", |a: Interval| a.ln()),
            Operator::make_constant("PI", around(PI)),
            Operator::make_constant("π", around(PI)),
            Operator::make_constant("E", around(E)),
            Operator::make_constant("e", around(E)),
            Operator::make_constant("TAU", around(TAU)),
            Operator::make_constant("τ", around(TAU)),
        ]
    }
}

/// Decimal literals with an optional exponent, for the interval re-parse.
mod literal {
    use exmex::MatchLiteral;
    // `exmex`'s default `NumberMatcher` takes digits and dots only, but its `unparse` writes the
    // constants it folds into derivatives in exponent form (`d/dz z^2/0.0036` is
    // `… /1.296e-5`): read with the default matcher the text no longer parses, and the whole
    // expression silently lost its interval extension — no Plantinga–Vegter test and no
    // target → fit measurement (issue 17: `x^2/0.81 + y^2/0.09 + z^2/0.0036 - 1` reported ∞).
    // An exponent only when digits follow, as in the grammar: `2e` stays `2` and the name `e`.
    exmex::literal_matcher_from_pattern!(
        DecimalMatcher,
        r"^([0-9]+\.?[0-9]*|\.[0-9]+)([eE][+-]?[0-9]+)?"
    );
}

type IntervalEx = FlatEx<Interval, IntervalOps, literal::DecimalMatcher>;

/// One compiled expression and, for each of its variables (in `exmex`'s order), the coordinate it
/// reads.
#[derive(Clone, Debug)]
struct Compiled<E> {
    ex: E,
    slots: Vec<usize>,
}

fn slots_of(names: &[String], dim: usize, text: &str) -> Result<Vec<usize>, FitError> {
    names
        .iter()
        .map(|name| {
            VARIABLES[..dim]
                .iter()
                .position(|v| v == name)
                .ok_or_else(|| FitError::Expression {
                    text: text.to_string(),
                    message: format!(
                        "unknown variable `{name}`; a {dim}-D expression may use {} and the \
                         constants {}",
                        VARIABLES[..dim].join(", "),
                        CONSTANTS.join(" ")
                    ),
                })
        })
        .collect()
}

/// A user expression `g(x, y[, z])` with its exact gradient and interval extensions.
#[derive(Clone, Debug)]
pub struct Expression {
    text: String,
    dim: usize,
    interval_value: Option<Compiled<IntervalEx>>,
    interval_partials: Option<Vec<Option<Compiled<IntervalEx>>>>,
    /// Second partials `[i][j]` over intervals, for the mean-value form of the gradient.
    interval_hessian: Option<Vec<Vec<Option<Compiled<IntervalEx>>>>>,
    /// `g` and `∇g` as evaluated ([`Tape`]); the `exmex` forms above give the symbolic
    /// derivatives and the interval extensions.
    tape: Tape,
}

impl Expression {
    /// Parses `text` as a function of the first `dim` of `x, y, z`.
    ///
    /// # Errors
    /// [`FitError::Expression`] when the text does not parse, uses another variable, or has no
    /// symbolic derivative.
    pub fn parse(text: &str, dim: usize) -> Result<Expression, FitError> {
        if text.len() > MAX_EXPRESSION_BYTES {
            return Err(FitError::Expression {
                text: text.chars().take(80).chain("…".chars()).collect(),
                message: format!(
                    "{} bytes, more than the {MAX_EXPRESSION_BYTES} an expression may have",
                    text.len()
                ),
            });
        }
        // `exmex`'s symbolic derivatives recurse once per term of a sum, tens of kilobytes of
        // stack a level: a 200-term sum overflowed the main thread's 8 MiB and aborted the
        // process (40 terms a test thread's 2 MiB). The work runs on a thread of its own with
        // a stack sized for the longest text taken; where no thread can be started, here.
        std::thread::scope(|scope| {
            match std::thread::Builder::new()
                .name("ism-fit expression".to_string())
                .stack_size(PARSE_STACK_BYTES)
                .spawn_scoped(scope, || Self::parse_here(text, dim))
            {
                Ok(handle) => handle
                    .join()
                    .unwrap_or_else(|panic| std::panic::resume_unwind(panic)),
                Err(_) => Self::parse_here(text, dim),
            }
        })
    }

    /// [`Expression::parse`] on the calling thread's stack.
    fn parse_here(text: &str, dim: usize) -> Result<Expression, FitError> {
        if !(1..=3).contains(&dim) {
            return Err(FitError::Options(format!(
                "dimension {dim} is not 1, 2 or 3"
            )));
        }
        let err = |message: String| FitError::Expression {
            text: text.to_string(),
            message,
        };
        let tree = parse_tree(text).map_err(err)?;
        let mut exmex_text = String::new();
        tree.to_exmex(&mut exmex_text);
        let ex = exmex::parse::<f64>(&exmex_text).map_err(|e| err(e.to_string()))?;
        let slots = slots_of(ex.var_names(), dim, text)?;
        let mut partials = vec![None; dim];
        for (var_index, &coord) in slots.iter().enumerate() {
            let d = ex
                .clone()
                .partial(var_index)
                .map_err(|e| err(format!("no derivative: {e}")))?;
            let d_slots = slots_of(d.var_names(), dim, text)?;
            partials[coord] = Some(Compiled {
                ex: d,
                slots: d_slots,
            });
        }
        // The interval versions re-parse the same texts; a function without an interval extension
        // (e.g. `atan`) still fits, only without the Plantinga–Vegter test.
        let to_interval = |f: &FlatEx<f64>| -> Option<Compiled<IntervalEx>> {
            let t = f.unparse();
            let t: &str = t;
            let ex = IntervalEx::parse(t).ok()?;
            let slots = slots_of(ex.var_names(), dim, text).ok()?;
            Some(Compiled { ex, slots })
        };
        let interval_value = to_interval(&ex);
        let interval_partials: Option<Vec<Option<Compiled<IntervalEx>>>> = partials
            .iter()
            .map(|p| match p {
                None => Some(None),
                Some(c) => to_interval(&c.ex).map(Some),
            })
            .collect();
        let interval_hessian: Option<Vec<Vec<Option<Compiled<IntervalEx>>>>> = partials
            .iter()
            .map(|p| -> Option<Vec<Option<Compiled<IntervalEx>>>> {
                let mut row = vec![None; dim];
                if let Some(c) = p {
                    for (var_index, &coord) in c.slots.iter().enumerate() {
                        let d2 = c.ex.clone().partial(var_index).ok()?;
                        row[coord] = Some(to_interval(&d2)?);
                    }
                }
                Some(row)
            })
            .collect();
        let (interval_value, interval_partials) = match (interval_value, interval_partials) {
            (Some(v), Some(p)) => (Some(v), Some(p)),
            _ => (None, None),
        };
        let tape = Tape::compile(&tree, dim)
            .ok_or_else(|| err("a name that is neither a coordinate nor a constant".to_string()))?;
        Ok(Expression {
            text: text.to_string(),
            dim,
            tape,
            interval_value,
            interval_partials,
            interval_hessian,
        })
    }

    /// The source text.
    pub fn text(&self) -> &str {
        &self.text
    }

    /// Whether interval enclosures are available (every function used has an interval version).
    pub fn has_interval_extension(&self) -> bool {
        self.interval_value.is_some()
    }
}

fn eval_interval(c: &Compiled<IntervalEx>, b: &[Interval]) -> Interval {
    let mut args = [Interval::default(); 3];
    for (a, &s) in args.iter_mut().zip(&c.slots) {
        *a = b[s];
    }
    c.ex.eval(&args[..c.slots.len()])
        .unwrap_or(Interval::ENTIRE)
}

impl ImplicitFunction for Expression {
    fn dim(&self) -> usize {
        self.dim
    }

    fn value(&self, p: &[f64]) -> f64 {
        self.tape.value(p)
    }

    fn gradient(&self, p: &[f64], gradient: &mut [f64]) -> f64 {
        self.tape.gradient(p, gradient)
    }

    /// One work space for the whole batch: [`Tape::gradient`]'s is cleared per point (a
    /// `memset` of the fixed-size buffer, 2.3 % of the torus preset's fit at 2e-4, issue 17).
    fn gradient_each(&self, points: &[[f64; 3]], out: &mut Vec<(f64, [f64; 3])>) {
        self.tape.gradient_each(self.dim, points, out);
    }

    /// Natural interval extensions intersected with mean-value forms around the box centre
    /// (`g(c) + □∇g·(box − c)`, and `∇g(c) + □H·(box − c)` for the gradient): the natural extension
    /// of an expanded polynomial loses all cancellation between its terms, while the mean-value
    /// form overestimates only to second order in the box size. Both enclose, so their
    /// intersection does.
    fn enclose(&self, lo: &[f64], hi: &[f64]) -> Option<Enclosure> {
        let value = self.interval_value.as_ref()?;
        let partials = self.interval_partials.as_ref()?;
        let boxes: Vec<Interval> = lo
            .iter()
            .zip(hi)
            .map(|(&a, &b)| Interval::new(a, b))
            .collect();
        let centre: Vec<Interval> = lo
            .iter()
            .zip(hi)
            .map(|(&a, &b)| Interval::point(0.5 * (a + b)))
            .collect();
        let offsets: Vec<Interval> = boxes.iter().zip(&centre).map(|(b, c)| *b - *c).collect();
        let partial_over = |d: &Option<Compiled<IntervalEx>>, over: &[Interval]| {
            d.as_ref()
                .map_or(Interval::point(0.0), |d| eval_interval(d, over))
        };
        let natural: Vec<Interval> = partials.iter().map(|d| partial_over(d, &boxes)).collect();
        let mut v = eval_interval(value, &centre);
        for (g, o) in natural.iter().zip(&offsets) {
            v = v + *g * *o;
        }
        let value = eval_interval(value, &boxes).intersect(v);
        let gradient = match &self.interval_hessian {
            Some(h) => natural
                .iter()
                .zip(partials.iter().zip(h))
                .map(|(nat, (d, row))| {
                    let mut g = partial_over(d, &centre);
                    for (hd, o) in row.iter().zip(&offsets) {
                        g = g + partial_over(hd, &boxes) * *o;
                    }
                    nat.intersect(g)
                })
                .collect(),
            None => natural,
        };
        Some(Enclosure { value, gradient })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn quotients_by_small_constants_keep_the_interval_extension() {
        // d/dz of z^2/0.0036 folds to a constant exmex writes as `1.296e-5`; the interval
        // re-parse must read it (issue 17: this ellipsoid had no enclosure, target → fit = ∞).
        let e = Expression::parse("x^2/0.81 + y^2/0.09 + z^2/0.0036 - 1", 3).unwrap();
        assert!(e.has_interval_extension());
        // The enclosure of a box holds g and ∇g of the closed form at points of the box.
        let (lo, hi) = ([0.5, -0.1, 0.01], [0.6, 0.05, 0.03]);
        let en = e.enclose(&lo, &hi).expect("an enclosure");
        let slack = |v: f64| 1e-12 * (1.0 + v.abs());
        for i in 0..=4 {
            for j in 0..=4 {
                for k in 0..=4 {
                    let t = [i as f64 / 4.0, j as f64 / 4.0, k as f64 / 4.0];
                    let p: Vec<f64> = (0..3).map(|a| lo[a] + t[a] * (hi[a] - lo[a])).collect();
                    let g = p[0] * p[0] / 0.81 + p[1] * p[1] / 0.09 + p[2] * p[2] / 0.0036 - 1.0;
                    let grad = [2.0 * p[0] / 0.81, 2.0 * p[1] / 0.09, 2.0 * p[2] / 0.0036];
                    assert!(en.value.lo - slack(g) <= g && g <= en.value.hi + slack(g));
                    for (d, iv) in grad.iter().zip(&en.gradient) {
                        assert!(
                            iv.lo - slack(*d) <= *d && *d <= iv.hi + slack(*d),
                            "{d} {iv:?}"
                        );
                    }
                }
            }
        }
        // The constant `e` after a number is still the constant, and `1e-3` a number.
        let e = Expression::parse("x - 2*e + y*1e-3", 2).unwrap();
        assert!(e.has_interval_extension());
        let v = e.enclose(&[1.0, 1.0], &[1.0, 1.0]).unwrap().value;
        let exact = 1.0 - 2.0 * std::f64::consts::E + 1e-3;
        assert!(v.lo <= exact && exact <= v.hi, "{v:?}");
    }

    #[test]
    fn the_tape_agrees_with_exmex_and_its_symbolic_derivatives() {
        // Truth: `exmex`'s own evaluation of the same text and its symbolic partials.
        let texts = [
            crate::presets::Preset::find("torus").unwrap().expr,
            crate::presets::Preset::find("genus2").unwrap().expr,
            "exp(-x)*cos(y) - ln(2 + z^2) + x^3 - 2^x + atan(x*y) + tanh(z)",
            "log10(3 + y) + log2(4 + x) + asinh(y) + acosh(2 + x^2) + atanh(0.5*y) + log(5 + z)",
            "asin(0.3*x) + acos(0.2*y) + sinh(z) + cosh(x) + tan(0.3*y) + sqrt(1.5 + x*y)",
            "PI*e - TAU + x/(1 + y^2) - -x^2 + (2 + y)^(1 + 0.5*x) + 0.28^2 - π*τ*E + z^0.5^2",
        ];
        for text in texts {
            let e = Expression::parse(text, 3).unwrap();
            let ex = exmex::parse::<f64>(&{
                let mut t = String::new();
                parse_tree(text).unwrap().to_exmex(&mut t);
                t
            })
            .unwrap();
            let slots = slots_of(ex.var_names(), 3, text).unwrap();
            let at = |f: &FlatEx<f64>, p: &[f64; 3]| {
                let s = slots_of(f.var_names(), 3, text).unwrap();
                let args: Vec<f64> = s.iter().map(|&k| p[k]).collect();
                f.eval(&args).unwrap()
            };
            for i in 0..200 {
                let t = i as f64;
                let p = [
                    0.9 * (0.37 * t).sin(),
                    0.9 * (0.71 * t + 1.0).cos(),
                    0.3 + 0.6 * (1.13 * t).sin().abs(),
                ];
                let mut grad = [0.0; 3];
                let v = e.gradient(&p, &mut grad);
                assert_eq!(v.to_bits(), e.value(&p).to_bits());
                let close = |a: f64, b: f64, rel: f64| (a - b).abs() <= rel * (1.0 + b.abs());
                let truth = at(&ex, &p);
                assert!(close(v, truth, 1e-13), "{text} at {p:?}: {v} vs {truth}");
                let mut want = [0.0; 3];
                for (var, &k) in slots.iter().enumerate() {
                    want[k] = at(&ex.clone().partial(var).unwrap(), &p);
                }
                for k in 0..3 {
                    assert!(
                        close(grad[k], want[k], 1e-11),
                        "{text} d/d{k} at {p:?}: {} vs {}",
                        grad[k],
                        want[k]
                    );
                }
            }
        }
    }

    #[test]
    fn parses_evaluates_and_differentiates() {
        let e = Expression::parse("x^2 + y^2 - 0.28^2", 2).unwrap();
        let mut g = [0.0; 2];
        let v = e.gradient(&[0.5, -0.25], &mut g);
        assert!((v - (0.25 + 0.0625 - 0.0784)).abs() < 1e-15);
        assert_eq!(g, [1.0, -0.5]);
        // A variable that does not occur has derivative 0.
        let e = Expression::parse("sin(x) - 0.5", 2).unwrap();
        let _ = e.gradient(&[0.3, 9.0], &mut g);
        assert!((g[0] - 0.3f64.cos()).abs() < 1e-15 && g[1] == 0.0);
    }

    /// A long sum parses on a test thread's 2 MiB stack (before session 24, `exmex`'s derivative
    /// recursed on the caller's stack: 40 terms overflowed a test thread, 200 the main thread),
    /// with the analytic value and gradient; a text past [`MAX_EXPRESSION_BYTES`] is refused
    /// with a typed error, not parsed at any cost.
    #[test]
    fn long_sums_parse_off_the_callers_stack_and_longer_texts_are_refused() {
        let terms = 200;
        let text = vec!["x^2"; terms].join("+") + "+y^2-1";
        assert!(text.len() <= MAX_EXPRESSION_BYTES);
        let e = Expression::parse(&text, 2).unwrap();
        let mut g = [0.0; 2];
        let (x, y) = (0.375, -0.5);
        let v = e.gradient(&[x, y], &mut g);
        // Truth: 200 x² + y² − 1 and (400 x, 2 y), exact in binary at these points.
        assert_eq!(v, terms as f64 * x * x + y * y - 1.0);
        assert_eq!(g, [2.0 * terms as f64 * x, 2.0 * y]);
        let long = vec!["x^2"; MAX_EXPRESSION_BYTES / 4 + 1].join("+");
        match Expression::parse(&long, 2) {
            Err(FitError::Expression { message, .. }) => {
                assert!(message.contains("more than the 1024"), "{message}")
            }
            other => panic!("expected a refusal, got {:?}", other.map(|_| ())),
        }
    }

    #[test]
    fn rejects_unknown_variables_and_syntax() {
        assert!(matches!(
            Expression::parse("x + w", 2),
            Err(FitError::Expression { .. })
        ));
        assert!(matches!(
            Expression::parse("x + z", 2),
            Err(FitError::Expression { .. })
        ));
        assert!(matches!(
            Expression::parse("x + (y", 2),
            Err(FitError::Expression { .. })
        ));
    }

    fn at(text: &str, p: &[f64]) -> f64 {
        Expression::parse(text, p.len()).unwrap().value(p)
    }

    // Expected values by hand arithmetic, with the precedence of mathematics, Python and Julia.
    #[test]
    fn unary_minus_binds_looser_than_power() {
        assert_eq!(at("-x^2", &[2.0]), -4.0);
        assert_eq!(at("-2^2 + 0*x", &[1.0]), -4.0);
        assert_eq!(at("(-x)^2", &[2.0]), 4.0);
        assert_eq!(at("0-x^2", &[2.0]), -4.0);
        assert_eq!(at("- -x", &[3.0]), 3.0);
        assert_eq!(at("+x", &[3.0]), 3.0);
        // The issue's circle: -x²-y²+0.25 at (0.5, 0.25) is -0.25 - 0.0625 + 0.25.
        assert_eq!(at("-x^2-y^2+0.25", &[0.5, 0.25]), -0.0625);
        // The exponent may carry a sign: 2^-x = 2^(-x).
        assert_eq!(at("2^-x", &[1.0]), 0.5);
        assert_eq!(at("x*-y", &[2.0, 3.0]), -6.0);
    }

    #[test]
    fn binary_operators_associate_conventionally() {
        // ^ to the right: 2^(3^2) = 2^9.
        assert_eq!(at("x^3^2", &[2.0]), 512.0);
        assert_eq!(at("x**3**2", &[2.0]), 512.0);
        // * and / to the left, at one level: (8/4)/2 and (8/4)*2.
        assert_eq!(at("x/4/2", &[8.0]), 1.0);
        assert_eq!(at("x/4*2", &[8.0]), 4.0);
        // + and - to the left, at one level: (2-3)-4 and (2-3)+4.
        assert_eq!(at("x-3-4", &[2.0]), -5.0);
        assert_eq!(at("x-3+4", &[2.0]), 3.0);
        // * before +, ^ before *: 1 + (2·(3^2)) = 19.
        assert_eq!(at("x + 2*3^2", &[1.0]), 19.0);
        assert_eq!(at("2*x^2/4", &[3.0]), 4.5);
    }

    #[test]
    fn numbers_constants_and_functions() {
        assert_eq!(at("1e-3*x", &[2000.0]), 2.0);
        assert_eq!(at("2.5E+1 - x", &[5.0]), 20.0);
        assert_eq!(at(".5*x", &[4.0]), 2.0);
        assert_eq!(at("sqrt(x) - 0.5", &[0.25]), 0.0);
        assert_eq!(at("-sqrt(x)^2", &[9.0]), -9.0);
        assert_eq!(at("PI*x", &[1.0]), std::f64::consts::PI);
        // The gradient of -x² is -2x.
        let e = Expression::parse("-x^2", 1).unwrap();
        let mut g = [0.0];
        e.gradient(&[3.0], &mut g);
        assert_eq!(g, [-6.0]);
    }

    fn message(text: &str) -> String {
        match Expression::parse(text, 2) {
            Err(FitError::Expression { message, .. }) => message,
            other => panic!("{text}: {other:?}"),
        }
    }

    #[test]
    fn grammar_lines_are_aligned() {
        // Every rule line is indented by two spaces (a `\` continuation would strip the first).
        for line in GRAMMAR.lines().take(8) {
            assert!(
                line.starts_with("  ") && !line.starts_with("   "),
                "{line:?}"
            );
        }
    }

    #[test]
    fn syntax_errors_say_where_and_what_was_expected() {
        assert_eq!(
            message("x^^2"),
            "expected a number, a variable, a constant, a function or `(` after `^`, found `^` at \
             character 3"
        );
        assert_eq!(
            message("x + (y"),
            "expected `)`, found the end of the expression (character 7)"
        );
        assert_eq!(
            message("2e"),
            "expected an operator (+ - * / ^) or the end, found `e` at character 2"
        );
        assert!(message("sin x").contains("needs its argument in parentheses"));
        assert!(message("foo(x)").starts_with("unknown function `foo`"));
        assert!(message("x # y").starts_with("unexpected character `#` at character 3"));
        assert_eq!(message("  "), "the expression is empty");
        assert!(message("x - ").contains("found the end of the expression"));
    }

    fn torus() -> Expression {
        Expression::parse(
            "(x^2 + y^2 + z^2 + 0.36 - 0.0625)^2 - 1.44*(x^2 + y^2) + sin(x*z)",
            3,
        )
        .unwrap()
    }

    /// The tape as compiled, before [`Tape::shared`].
    fn unshared(text: &str, dim: usize) -> Tape {
        let tree = parse_tree(text).unwrap();
        let mut tape = Tape {
            ins: Vec::new(),
            uses: [false; 3],
        };
        tape.push(&tree, dim).unwrap();
        tape
    }

    #[test]
    fn shared_tapes_compute_the_same_bits_with_fewer_instructions() {
        let cases = [
            (
                "(x^2 + y^2 + z^2 + 0.36 - 0.0625)^2 - 1.44*(x^2 + y^2)",
                3,
                21,
                16,
            ),
            ("x^2 + y^2 + z^2 - 0.36", 3, 10, 10),
            ("(x^2*(1 - x^2) - y^2)^2 + z^2 - 0.01", 3, 16, 14),
            (
                "sin(x*z) + sin(x*z)*2 - -0*x + 0*x - (x/y)^1.5 + 2^(x/y)",
                3,
                30,
                19,
            ),
            // The root repeats an earlier instruction's key only through its operands.
            ("x", 2, 1, 1),
        ];
        let mut rng: u64 = 0x9e37_79b9_7f4a_7c15;
        for (text, dim, before, after) in cases {
            let (old, new) = (
                unshared(text, dim),
                Tape::compile(&parse_tree(text).unwrap(), dim).unwrap(),
            );
            assert_eq!((old.ins.len(), new.ins.len()), (before, after), "{text}");
            for _ in 0..1000 {
                let mut p = [0.0; 3];
                for x in &mut p {
                    rng ^= rng << 13;
                    rng ^= rng >> 7;
                    rng ^= rng << 17;
                    *x = (rng >> 11) as f64 / (1u64 << 53) as f64 * 4.0 - 2.0;
                }
                let (mut g0, mut g1) = ([0.0; 3], [0.0; 3]);
                let (v0, v1) = (old.gradient(&p, &mut g0), new.gradient(&p, &mut g1));
                assert_eq!(v0.to_bits(), v1.to_bits(), "{text} at {p:?}");
                assert_eq!(old.value(&p).to_bits(), new.value(&p).to_bits());
                assert_eq!(
                    g0.map(f64::to_bits),
                    g1.map(f64::to_bits),
                    "{text} at {p:?}"
                );
            }
        }
    }

    /// The batch gradient reuses one work space: every point must still get the bits of its own
    /// [`ImplicitFunction::gradient`] (zero past the dimension), whatever came before it.
    #[test]
    fn gradient_each_is_the_gradient_at_every_point() {
        // Longer than the stack buffers of `Tape::gradient` (> 96 instructions), summed as a
        // balanced tree: a chain of 40 sums nests too deep for the parser on a test thread.
        fn balanced(terms: &[String]) -> String {
            match terms {
                [t] => t.clone(),
                _ => {
                    let (a, b) = terms.split_at(terms.len() / 2);
                    format!("({} + {})", balanced(a), balanced(b))
                }
            }
        }
        let long = balanced(&(1..=40).map(|k| format!("{k}*x^2")).collect::<Vec<_>>());
        let cases = [
            (
                "(x^2 + y^2 + z^2 + 0.36 - 0.0625)^2 - 1.44*(x^2 + y^2) + sin(x*z)",
                3,
            ),
            ("x^2 + z^2 - 0.25", 3),
            ("(x^2+y^2-1)^3-x^2*y^3", 2),
            ("x/y + sqrt(x) - ln(y)", 2),
            (&long[..], 3),
        ];
        let mut rng: u64 = 0x2545_f491_4f6c_dd1d;
        for (text, dim) in cases {
            let e = Expression::parse(text, dim).unwrap();
            if text == long {
                assert!(e.tape.ins.len() > TAPE_LONG, "{}", e.tape.ins.len());
            }
            let mut points: Vec<[f64; 3]> = vec![[0.0; 3], [-1.0, 0.0, 0.5]];
            for _ in 0..200 {
                let mut p = [0.0; 3];
                for x in &mut p {
                    rng ^= rng << 13;
                    rng ^= rng >> 7;
                    rng ^= rng << 17;
                    *x = (rng >> 11) as f64 / (1u64 << 53) as f64 * 4.0 - 2.0;
                }
                points.push(p);
            }
            let mut out = vec![(7.0, [7.0; 3])];
            e.gradient_each(&points, &mut out);
            assert_eq!(out.len(), points.len(), "{text}");
            for (p, (v, g)) in points.iter().zip(&out) {
                let mut g0 = [0.0; 3];
                let v0 = e.gradient(&p[..dim], &mut g0[..dim]);
                assert_eq!(v.to_bits(), v0.to_bits(), "{text} at {p:?}");
                assert_eq!(g.map(f64::to_bits), g0.map(f64::to_bits), "{text} at {p:?}");
            }
        }
    }

    proptest! {
        // Cross-check 1: the symbolic gradient against central differences.
        #[test]
        fn gradient_matches_finite_differences(x in -1.0f64..1.0, y in -1.0f64..1.0, z in -1.0f64..1.0) {
            let e = torus();
            let p = [x, y, z];
            let mut g = [0.0; 3];
            e.gradient(&p, &mut g);
            for k in 0..3 {
                let h = 1e-6;
                let mut a = p; a[k] += h;
                let mut b = p; b[k] -= h;
                let fd = (e.value(&a) - e.value(&b)) / (2.0 * h);
                prop_assert!((fd - g[k]).abs() < 1e-6 * (1.0 + g[k].abs()), "k={} fd={} g={}", k, fd, g[k]);
            }
        }

        // Cross-check 2: interval enclosures contain the point values and derivatives.
        #[test]
        fn enclosures_contain_point_values(x in -1.0f64..0.8, y in -1.0f64..0.8, z in -1.0f64..0.8,
                                           s in 0.0f64..=1.0, t in 0.0f64..=1.0, u in 0.0f64..=1.0) {
            let e = torus();
            let lo = [x, y, z];
            let hi = [x + 0.2, y + 0.2, z + 0.2];
            let p = [x + 0.2 * s, y + 0.2 * t, z + 0.2 * u];
            let enc = e.enclose(&lo, &hi).unwrap();
            prop_assert!(enc.value.contains(e.value(&p)));
            let mut g = [0.0; 3];
            e.gradient(&p, &mut g);
            for (bound, gk) in enc.gradient.iter().zip(g) {
                prop_assert!(bound.contains(gk));
            }
        }
    }
}
