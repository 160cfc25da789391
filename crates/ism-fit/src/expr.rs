//! Implicit functions `g: Rⁿ → R`: the [`ImplicitFunction`] trait and user expressions.
//!
//! An [`Expression`] (variables `x`, `y`, `z`) is read by this module's own parser with the
//! conventional precedence of mathematics, Python and Julia (see [`GRAMMAR`]) and compiled to
//! straight-line code: `g` and its exact gradient (forward mode) in `f64` (`Tape`), and `g`
//! with its symbolic first and second partial derivatives over [`Interval`] for the
//! Plantinga–Vegter test (`IntervalForms`). `exmex` checks the text once more, handed to it
//! fully parenthesized: `exmex` alone lets unary minus bind tighter than `^` (`-x^2` would be
//! `(-x)^2`) and has no exponent notation (`1e-3`); the tests hold the code to `exmex`'s own
//! evaluation and derivatives.

use std::collections::HashMap;

use exmex::prelude::*;
#[cfg(test)]
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
    /// A literal and whether it is exactly that double ([`literal_is_exact`]).
    Number(f64, bool),
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
            Node::Number(v, _) => out.push_str(&format!("{v}")),
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
    /// A literal and whether it is exactly that double ([`literal_is_exact`]).
    Number(f64, bool),
    Name(String),
    /// One of `+ - * / ^` (`**` is read as `^`).
    Op(char),
    Open,
    Close,
}

impl Token {
    fn describe(&self) -> String {
        match self {
            Token::Number(v, _) => format!("the number {v}"),
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
            tokens.push((Token::Number(value, literal_is_exact(&literal)), start + 1));
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

/// Whether the decimal `literal` (digits, an optional fraction and exponent, as [`tokenize`]
/// reads them) is exactly the double it reads as. Only integers below 10¹⁵ (< 2⁵³, all doubles)
/// are said to be; other literals, even exact ones such as `0.5`, are widened by one rounding in
/// the interval forms ([`Interval::around`]), which only costs width.
fn literal_is_exact(literal: &str) -> bool {
    let (mantissa, exponent) = match literal.find(['e', 'E']) {
        Some(i) => (&literal[..i], literal[i + 1..].parse::<i64>()),
        None => (literal, Ok(0)),
    };
    let Ok(exponent) = exponent else {
        return false;
    };
    let (int, frac) = mantissa.split_once('.').unwrap_or((mantissa, ""));
    let frac = frac.trim_end_matches('0');
    let digits = format!("{int}{frac}");
    let digits = digits.trim_start_matches('0');
    let significant = digits.trim_end_matches('0');
    if significant.is_empty() {
        return true;
    }
    // The value is `significant · 10^scale`.
    let scale = exponent - frac.len() as i64 + (digits.len() - significant.len()) as i64;
    scale >= 0 && significant.len() as i64 + scale <= 15
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
            Token::Number(v, exact) => {
                self.at += 1;
                Ok(Node::Number(v, exact))
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
/// 21 GB and 112 CPU-s (session 24, `ism fit --expr`). Since session 26 no symbolic derivative
/// comes from `exmex`; the limit stays as the bound on the parser's and the builders' recursion.
pub const MAX_EXPRESSION_BYTES: usize = 1024;
/// The stack of the thread [`Expression::parse`] runs on: `exmex`'s derivative of a sum recurses
/// once per term at tens of kilobytes a level (a 200-term sum overflowed the main thread's
/// 8 MiB). Address space only: pages are touched as the recursion reaches them.
const PARSE_STACK_BYTES: usize = 256 << 20;

const TAPE_SHORT: usize = 24;
const TAPE_LONG: usize = 96;

/// Points [`Tape::gradient_each`] runs through the tape together: enough to pay an instruction's
/// dispatch once for several points, few enough that a torus tape's work space (16 slots of
/// 256 bytes) stays in the first-level cache.
const LANES: usize = 8;

/// One slot of [`Tape::run_lanes`]: the value and gradient of [`LANES`] points.
#[derive(Clone, Copy, Debug)]
struct Slot {
    v: [f64; LANES],
    d: [[f64; LANES]; 3],
}

thread_local! {
    /// [`Tape::gradient_each`]'s work space on this thread.
    static LANE_SLOTS: std::cell::RefCell<Vec<Slot>> = const { std::cell::RefCell::new(Vec::new()) };
    /// [`IntervalTape::eval`]'s work space on this thread.
    static INTERVAL_SLOTS: std::cell::RefCell<Vec<Interval>> =
        const { std::cell::RefCell::new(Vec::new()) };
}

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
            Node::Number(v, _) => self.emit(Ins::Const(*v)),
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

    /// [`Tape::gradient`] at each point's first `dim` coordinates into `out`, bit for bit, run
    /// [`LANES`] points at a time instruction by instruction ([`Tape::run_lanes`]): the dispatch on
    /// each instruction and its operand look-ups are paid once per group instead of once per
    /// point, and the per-lane loops compile to packed arithmetic. Issue 17, session 26: the
    /// point-by-point loop was 11 % of a torus fit at 1e-4 (`perf`), the largest item of this file.
    fn gradient_each(&self, dim: usize, points: &[[f64; 3]], out: &mut Vec<(f64, [f64; 3])>) {
        const ZERO: Slot = Slot {
            v: [0.0; LANES],
            d: [[0.0; LANES]; 3],
        };
        let n = self.ins.len();
        // The thread's work space, kept between calls: the optimizer calls this once per trial
        // step (5.6 M times in a torus fit at 1e-4), and a fresh one on the stack is cleared
        // each time (6 KB: 5 % of the instructions of a torus fit at 1e-2, callgrind). Every
        // slot is written before it is read, so it needs no clearing between calls or groups.
        LANE_SLOTS.with_borrow_mut(|work| {
            if work.len() < n {
                work.resize(n, ZERO);
            }
            self.gradient_groups(dim, points, &mut work[..n], out);
        });
    }

    /// [`Tape::gradient_each`] through the work space `r` (one slot per instruction).
    fn gradient_groups(
        &self,
        dim: usize,
        points: &[[f64; 3]],
        r: &mut [Slot],
        out: &mut Vec<(f64, [f64; 3])>,
    ) {
        let n = self.ins.len();
        out.clear();
        out.reserve(points.len());
        for group in points.chunks(LANES) {
            let mut x = [[0.0; LANES]; 3];
            // Lanes past the group's end repeat its last point; their results are dropped.
            for (l, lane) in (0..LANES).zip(
                group
                    .iter()
                    .chain(std::iter::repeat(&group[group.len() - 1])),
            ) {
                for k in 0..dim {
                    x[k][l] = lane[k];
                }
            }
            self.run_lanes(&x, r);
            let last = &r[n - 1];
            out.extend((0..group.len()).map(|l| {
                let mut grad = [0.0; 3];
                for (k, g) in grad.iter_mut().enumerate().take(dim) {
                    // A coordinate that does not occur has derivative 0 exactly (not 0·∞ = NaN).
                    *g = if self.uses[k] { last.d[k][l] } else { 0.0 };
                }
                (last.v[l], grad)
            }));
        }
    }

    /// [`Tape::run_gradient`] on [`LANES`] points at once (coordinate `k` of lane `l` in
    /// `x[k][l]`): each lane gets the same operations on the same numbers in the same order as
    /// [`Tape::run_gradient`] gives its point, so the same bits. Lanes indexed in plain loops (the
    /// form the compiler packs), and `· −1` as in [`Tape::run_gradient`] (`-x` would flip a NaN's
    /// sign bit where the product keeps it).
    #[allow(clippy::needless_range_loop, clippy::neg_multiply)]
    fn run_lanes(&self, x: &[[f64; LANES]; 3], r: &mut [Slot]) {
        for (i, ins) in self.ins.iter().enumerate() {
            let (done, rest) = r.split_at_mut(i);
            let o = &mut rest[0];
            match *ins {
                Ins::Const(c) => {
                    o.v = [c; LANES];
                    o.d = [[0.0; LANES]; 3];
                }
                Ins::Var(k) => {
                    o.v = x[k];
                    o.d = [[0.0; LANES]; 3];
                    o.d[k] = [1.0; LANES];
                }
                Ins::Neg(a) => {
                    let a = &done[a];
                    for l in 0..LANES {
                        o.v[l] = -a.v[l];
                    }
                    for k in 0..3 {
                        for l in 0..LANES {
                            o.d[k][l] = a.d[k][l] * -1.0;
                        }
                    }
                }
                Ins::Add(a, b) => {
                    let (a, b) = (&done[a], &done[b]);
                    for l in 0..LANES {
                        o.v[l] = a.v[l] + b.v[l];
                    }
                    for k in 0..3 {
                        for l in 0..LANES {
                            o.d[k][l] = a.d[k][l] + b.d[k][l];
                        }
                    }
                }
                Ins::Sub(a, b) => {
                    let (a, b) = (&done[a], &done[b]);
                    for l in 0..LANES {
                        o.v[l] = a.v[l] - b.v[l];
                    }
                    for k in 0..3 {
                        for l in 0..LANES {
                            o.d[k][l] = a.d[k][l] - b.d[k][l];
                        }
                    }
                }
                Ins::Mul(a, b) => {
                    let (a, b) = (&done[a], &done[b]);
                    for l in 0..LANES {
                        o.v[l] = a.v[l] * b.v[l];
                    }
                    for k in 0..3 {
                        for l in 0..LANES {
                            o.d[k][l] = a.d[k][l] * b.v[l] + a.v[l] * b.d[k][l];
                        }
                    }
                }
                Ins::Div(a, b) => {
                    let (a, b) = (&done[a], &done[b]);
                    for l in 0..LANES {
                        o.v[l] = a.v[l] / b.v[l];
                    }
                    for k in 0..3 {
                        for l in 0..LANES {
                            o.d[k][l] = (a.d[k][l] - o.v[l] * b.d[k][l]) / b.v[l];
                        }
                    }
                }
                Ins::PowConst(a, c) => {
                    let a = &done[a];
                    let mut s = [0.0; LANES];
                    if c == 2.0 {
                        for l in 0..LANES {
                            o.v[l] = a.v[l] * a.v[l];
                            s[l] = 2.0 * a.v[l];
                        }
                    } else if c == 1.0 {
                        for l in 0..LANES {
                            o.v[l] = power(a.v[l], c);
                            s[l] = 1.0;
                        }
                    } else {
                        for l in 0..LANES {
                            o.v[l] = power(a.v[l], c);
                            s[l] = c * power(a.v[l], c - 1.0);
                        }
                    }
                    for k in 0..3 {
                        for l in 0..LANES {
                            o.d[k][l] = a.d[k][l] * s[l];
                        }
                    }
                }
                Ins::Pow(a, b) => {
                    let (a, b) = (&done[a], &done[b]);
                    for l in 0..LANES {
                        let (x, y) = (a.v[l], b.v[l]);
                        let v = power(x, y);
                        // d(x^y) = x^y (y' ln x + y x'/x).
                        let (ln, q) = (x.ln(), y / x);
                        o.v[l] = v;
                        for k in 0..3 {
                            o.d[k][l] = v * (b.d[k][l] * ln + q * a.d[k][l]);
                        }
                    }
                }
                Ins::Call(f, a) => {
                    let a = &done[a];
                    let mut s = [0.0; LANES];
                    for l in 0..LANES {
                        o.v[l] = f.apply(a.v[l]);
                        s[l] = f.derivative(a.v[l], o.v[l]);
                    }
                    for k in 0..3 {
                        for l in 0..LANES {
                            o.d[k][l] = a.d[k][l] * s[l];
                        }
                    }
                }
            }
        }
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

/// Functions of one argument with an interval extension in [`crate::interval`]; an expression
/// using any other ([`Fun`]) has no interval forms and fits without the Plantinga–Vegter test.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
enum IntervalFun {
    Sqrt,
    Exp,
    Ln,
    Sin,
    Cos,
    Tan,
}

impl IntervalFun {
    fn of(f: Fun) -> Option<IntervalFun> {
        Some(match f {
            Fun::Sqrt => IntervalFun::Sqrt,
            Fun::Exp => IntervalFun::Exp,
            Fun::Ln => IntervalFun::Ln,
            Fun::Sin => IntervalFun::Sin,
            Fun::Cos => IntervalFun::Cos,
            Fun::Tan => IntervalFun::Tan,
            _ => return None,
        })
    }

    fn apply(self, a: Interval) -> Interval {
        match self {
            IntervalFun::Sqrt => a.sqrt(),
            IntervalFun::Exp => a.exp(),
            IntervalFun::Ln => a.ln(),
            IntervalFun::Sin => a.sin(),
            IntervalFun::Cos => a.cos(),
            IntervalFun::Tan => a.tan(),
        }
    }
}

/// One instruction of an [`IntervalTape`]; operands are earlier slots.
#[derive(Clone, Copy, Debug, PartialEq)]
enum IntervalIns {
    Const(Interval),
    Var(usize),
    Neg(usize),
    Add(usize, usize),
    Sub(usize, usize),
    Mul(usize, usize),
    /// `a·a`, as [`Interval::sqr`]: never below 0, unlike the product of two independent factors.
    Sqr(usize),
    Div(usize, usize),
    /// [`Interval::pow`]: repeated products for an exact integer exponent, `exp(b·ln a)` otherwise.
    Pow(usize, usize),
    Call(IntervalFun, usize),
}

impl IntervalIns {
    /// The instruction's identity for sharing: constants by their bits, operations by operands.
    fn key(self) -> (u8, usize, usize, u64, u64) {
        match self {
            IntervalIns::Const(c) => (0, 0, 0, c.lo.to_bits(), c.hi.to_bits()),
            IntervalIns::Var(k) => (1, k, 0, 0, 0),
            IntervalIns::Neg(a) => (2, a, 0, 0, 0),
            IntervalIns::Add(a, b) => (3, a, b, 0, 0),
            IntervalIns::Sub(a, b) => (4, a, b, 0, 0),
            IntervalIns::Mul(a, b) => (5, a, b, 0, 0),
            IntervalIns::Sqr(a) => (6, a, 0, 0, 0),
            IntervalIns::Div(a, b) => (7, a, b, 0, 0),
            IntervalIns::Pow(a, b) => (8, a, b, 0, 0),
            IntervalIns::Call(f, a) => (9, a, f as usize, 0, 0),
        }
    }

    /// The same instruction reading `map[a]` for each operand `a`.
    fn renumbered(self, map: &[usize]) -> IntervalIns {
        let m = |a: usize| map[a];
        match self {
            IntervalIns::Const(c) => IntervalIns::Const(c),
            IntervalIns::Var(k) => IntervalIns::Var(k),
            IntervalIns::Neg(a) => IntervalIns::Neg(m(a)),
            IntervalIns::Add(a, b) => IntervalIns::Add(m(a), m(b)),
            IntervalIns::Sub(a, b) => IntervalIns::Sub(m(a), m(b)),
            IntervalIns::Mul(a, b) => IntervalIns::Mul(m(a), m(b)),
            IntervalIns::Sqr(a) => IntervalIns::Sqr(m(a)),
            IntervalIns::Div(a, b) => IntervalIns::Div(m(a), m(b)),
            IntervalIns::Pow(a, b) => IntervalIns::Pow(m(a), m(b)),
            IntervalIns::Call(f, a) => IntervalIns::Call(f, m(a)),
        }
    }

    /// The operand slots.
    fn operands(self) -> [Option<usize>; 2] {
        match self {
            IntervalIns::Const(_) | IntervalIns::Var(_) => [None, None],
            IntervalIns::Neg(a) | IntervalIns::Sqr(a) | IntervalIns::Call(_, a) => [Some(a), None],
            IntervalIns::Add(a, b)
            | IntervalIns::Sub(a, b)
            | IntervalIns::Mul(a, b)
            | IntervalIns::Div(a, b)
            | IntervalIns::Pow(a, b) => [Some(a), Some(b)],
        }
    }

    /// The enclosure of the instruction's result from enclosures `r` of the earlier slots.
    fn eval(self, x: &[Interval], r: &[Interval]) -> Interval {
        match self {
            IntervalIns::Const(c) => c,
            IntervalIns::Var(k) => x[k],
            IntervalIns::Neg(a) => -r[a],
            IntervalIns::Add(a, b) => r[a] + r[b],
            IntervalIns::Sub(a, b) => r[a] - r[b],
            IntervalIns::Mul(a, b) => r[a] * r[b],
            IntervalIns::Sqr(a) => r[a].sqr(),
            IntervalIns::Div(a, b) => r[a] / r[b],
            IntervalIns::Pow(a, b) => r[a].pow(r[b]),
            IntervalIns::Call(f, a) => f.apply(r[a]),
        }
    }
}

/// Straight-line interval code with several results: the interval forms of an [`Expression`]
/// (its value, symbolic first and second partial derivatives), evaluated with the conservative
/// arithmetic of [`crate::interval`] in one pass without allocation. Issue 17, session 26: the
/// same forms through `exmex` (one `FlatEx<Interval>` evaluation per form, 16 per box for a 3-D
/// expression, each collecting its operands in `SmallVec`s) were ~30 % of the instructions of a
/// torus fit at 3e-3.
#[derive(Clone, Debug, PartialEq)]
struct IntervalTape {
    ins: Vec<IntervalIns>,
    /// The slot of each result; `None` for a result that is exactly 0 (a derivative by a
    /// coordinate the expression does not read).
    outputs: Vec<Option<usize>>,
}

impl IntervalTape {
    /// Each result over the box `x` (one interval per coordinate) into `out`.
    /// The work space is the thread's, kept between calls (as [`Tape::gradient_each`]'s):
    /// every slot is written before it is read.
    fn eval(&self, x: &[Interval], out: &mut [Interval]) {
        let n = self.ins.len();
        INTERVAL_SLOTS.with_borrow_mut(|work| {
            if work.len() < n {
                work.resize(n, Interval::default());
            }
            self.run(x, &mut work[..n], out);
        });
    }

    fn run(&self, x: &[Interval], r: &mut [Interval], out: &mut [Interval]) {
        for (i, ins) in self.ins.iter().enumerate() {
            r[i] = ins.eval(x, r);
        }
        for (o, slot) in out.iter_mut().zip(&self.outputs) {
            *o = slot.map_or(Interval::point(0.0), |s| r[s]);
        }
    }
}

/// Builds interval code from an expression tree and differentiates it symbolically: every
/// instruction is entered once (shared), operations on constants are folded in interval
/// arithmetic, and the structural zeros and ones of derivatives are left out.
#[derive(Default)]
struct IntervalBuilder {
    ins: Vec<IntervalIns>,
    seen: HashMap<(u8, usize, usize, u64, u64), usize>,
}

/// Integers whose sums, differences and products the builder folds exactly: below 2⁵², a
/// rounded result of integers is the exact one.
const EXACT_INTEGER: f64 = 4_503_599_627_370_496.0;

impl IntervalBuilder {
    fn constant(&self, slot: usize) -> Option<Interval> {
        match self.ins[slot] {
            IntervalIns::Const(c) => Some(c),
            _ => None,
        }
    }

    /// Whether `slot` is the exact constant `v`.
    fn is(&self, slot: usize, v: f64) -> bool {
        self.constant(slot) == Some(Interval::point(v))
    }

    fn point(&mut self, v: f64) -> usize {
        self.emit(IntervalIns::Const(Interval::point(v)))
    }

    /// The slot computing `ins`, simplified and shared.
    fn emit(&mut self, ins: IntervalIns) -> usize {
        use IntervalIns as I;
        if let I::Mul(a, b) = ins {
            if let Some(s) = self
                .scaled_square(a, b)
                .or_else(|| self.scaled_square(b, a))
            {
                return s;
            }
        }
        // Identities that hold wherever the operands are defined (`0·a = 0` also where an
        // enclosure of `a` is unbounded: the factor 0 is a structural zero of a derivative, the
        // true product is 0 wherever `a` is finite, and where it is not the function is not
        // defined either).
        let ins = match ins {
            I::Add(a, b) if self.is(a, 0.0) => return b,
            I::Add(a, b) | I::Sub(a, b) if self.is(b, 0.0) => return a,
            I::Sub(a, b) if self.is(a, 0.0) => I::Neg(b),
            I::Mul(a, _) | I::Div(a, _) if self.is(a, 0.0) => return a,
            I::Mul(_, b) if self.is(b, 0.0) => return b,
            I::Mul(a, b) if self.is(a, 1.0) => return b,
            I::Mul(a, b) | I::Div(a, b) if self.is(b, 1.0) => return a,
            I::Mul(a, b) if a == b => I::Sqr(a),
            I::Neg(a) => match self.ins[a] {
                I::Neg(b) => return b,
                _ => ins,
            },
            I::Pow(a, b) if self.is(b, 1.0) => return a,
            I::Pow(a, b) if self.is(b, 2.0) => I::Sqr(a),
            // Commutative: one order, so `a·b` and `b·a` are shared.
            I::Add(a, b) if a > b => I::Add(b, a),
            I::Mul(a, b) if a > b => I::Mul(b, a),
            _ => ins,
        };
        let ins = match self.fold(ins) {
            Some(c) => I::Const(c),
            None => ins,
        };
        let key = ins.key();
        if let Some(&at) = self.seen.get(&key) {
            return at;
        }
        self.ins.push(ins);
        self.seen.insert(key, self.ins.len() - 1);
        self.ins.len() - 1
    }

    /// `(c·q)·q` as `c·q²` (`p` = `c·q`, `c` a constant): the second derivative of `a²` by one
    /// coordinate twice is `(2a')·a'`, whose product of independent factors goes below 0 where
    /// `a'` may change sign.
    fn scaled_square(&mut self, p: usize, q: usize) -> Option<usize> {
        let IntervalIns::Mul(x, y) = self.ins[p] else {
            return None;
        };
        let c = match (x == q, y == q) {
            (true, _) => y,
            (_, true) => x,
            _ => return None,
        };
        self.constant(c)?;
        let s = self.emit(IntervalIns::Sqr(q));
        Some(self.emit(IntervalIns::Mul(c, s)))
    }

    /// `ins` over constant operands: exact for sums, differences and products of integers below
    /// [`EXACT_INTEGER`] (so `x^(3-1)` keeps the exact exponent 2 and its repeated products),
    /// otherwise the enclosure of the interval operation.
    fn fold(&self, ins: IntervalIns) -> Option<Interval> {
        let c = |a: usize| self.constant(a);
        let operands = ins.operands();
        let mut values = [Interval::default(); 2];
        for (v, a) in values.iter_mut().zip(operands) {
            if let Some(a) = a {
                *v = c(a)?;
            }
        }
        // Not for a constant or a coordinate.
        operands[0]?;
        let exact_integer = |v: Interval| v.lo == v.hi && v.lo.fract() == 0.0;
        let [a, b] = values;
        let exact = match ins {
            IntervalIns::Neg(_) => Some(-a.lo),
            IntervalIns::Add(..) => Some(a.lo + b.lo),
            IntervalIns::Sub(..) => Some(a.lo - b.lo),
            IntervalIns::Mul(..) => Some(a.lo * b.lo),
            _ => None,
        };
        if let Some(v) = exact {
            let operands_exact = exact_integer(a) && (operands[1].is_none() || exact_integer(b));
            if operands_exact && v.abs() < EXACT_INTEGER {
                return Some(Interval::point(v));
            }
        }
        Some(match ins {
            IntervalIns::Neg(_) => -a,
            IntervalIns::Add(..) => a + b,
            IntervalIns::Sub(..) => a - b,
            IntervalIns::Mul(..) => a * b,
            IntervalIns::Sqr(_) => a.sqr(),
            IntervalIns::Div(..) => a / b,
            IntervalIns::Pow(..) => a.pow(b),
            IntervalIns::Call(f, _) => f.apply(a),
            IntervalIns::Const(_) | IntervalIns::Var(_) => return None,
        })
    }

    /// Appends `node`'s code and returns its slot; `None` for a name that is neither a
    /// coordinate of `dim` nor a constant, or a function without an interval extension.
    fn push(&mut self, node: &Node, dim: usize) -> Option<usize> {
        use std::f64::consts::{E, PI, TAU};
        Some(match node {
            // A literal that is not exactly its double lies within half an ulp of it.
            Node::Number(v, true) => self.point(*v),
            Node::Number(v, false) => self.emit(IntervalIns::Const(Interval::around(*v))),
            Node::Name(n) => match VARIABLES[..dim].iter().position(|v| v == n) {
                Some(k) => self.emit(IntervalIns::Var(k)),
                None => {
                    let c = match n.as_str() {
                        "PI" | "π" => PI,
                        "E" | "e" => E,
                        "TAU" | "τ" => TAU,
                        _ => return None,
                    };
                    self.emit(IntervalIns::Const(Interval::around(c)))
                }
            },
            Node::Negate(a) => {
                let a = self.push(a, dim)?;
                self.emit(IntervalIns::Neg(a))
            }
            Node::Call(f, a) => {
                let f = IntervalFun::of(Fun::of(f)?)?;
                let a = self.push(a, dim)?;
                self.emit(IntervalIns::Call(f, a))
            }
            Node::Binary(op, a, b) => {
                let a = self.push(a, dim)?;
                let b = self.push(b, dim)?;
                self.emit(match op {
                    '+' => IntervalIns::Add(a, b),
                    '-' => IntervalIns::Sub(a, b),
                    '*' => IntervalIns::Mul(a, b),
                    '/' => IntervalIns::Div(a, b),
                    _ => IntervalIns::Pow(a, b),
                })
            }
        })
    }

    /// `a + b` of derivatives (`None`: exactly 0).
    fn add(&mut self, a: Option<usize>, b: Option<usize>) -> Option<usize> {
        match (a, b) {
            (Some(a), Some(b)) => Some(self.emit(IntervalIns::Add(a, b))),
            (a, None) => a,
            (None, b) => b,
        }
    }

    /// `a · b` with `b` a derivative (`None`: exactly 0).
    fn times(&mut self, a: usize, b: Option<usize>) -> Option<usize> {
        b.map(|b| self.emit(IntervalIns::Mul(a, b)))
    }

    /// The derivative by coordinate `k` of every slot below `upto` (`None`: exactly 0), by the
    /// rules of calculus on the code itself; the new code is appended (and shared).
    fn derivatives(&mut self, upto: usize, k: usize) -> Vec<Option<usize>> {
        use IntervalIns as I;
        let mut d: Vec<Option<usize>> = Vec::with_capacity(upto);
        for i in 0..upto {
            let ins = self.ins[i];
            let di = match ins {
                I::Const(_) => None,
                I::Var(j) => (j == k).then(|| self.point(1.0)),
                I::Neg(a) => d[a].map(|da| self.emit(I::Neg(da))),
                I::Add(a, b) => self.add(d[a], d[b]),
                I::Sub(a, b) => match (d[a], d[b]) {
                    (da, None) => da,
                    (None, Some(db)) => Some(self.emit(I::Neg(db))),
                    (Some(da), Some(db)) => Some(self.emit(I::Sub(da, db))),
                },
                // (ab)' = a'b + ab'.
                I::Mul(a, b) => {
                    let l = d[a].map(|da| self.emit(I::Mul(da, b)));
                    let r = self.times(a, d[b]);
                    self.add(l, r)
                }
                // (a²)' = (2a)·a'.
                I::Sqr(a) => d[a].map(|da| {
                    let two = self.point(2.0);
                    let f = self.emit(I::Mul(two, a));
                    self.emit(I::Mul(f, da))
                }),
                // (a/b)' = (a' − (a/b)·b')/b.
                I::Div(a, b) => {
                    let q = self.times(i, d[b]);
                    let top = match (d[a], q) {
                        (da, None) => da,
                        (None, Some(q)) => Some(self.emit(I::Neg(q))),
                        (Some(da), Some(q)) => Some(self.emit(I::Sub(da, q))),
                    };
                    top.map(|t| self.emit(I::Div(t, b)))
                }
                I::Pow(a, b) => match self.constant(b) {
                    // (a^c)' = (c·a^(c−1))·a'; for an exact integer c the exponent c − 1 is exact.
                    Some(c) => match d[a] {
                        None => None,
                        Some(da) => {
                            let lower = if c.lo == c.hi && c.lo.fract() == 0.0 {
                                self.point(c.lo - 1.0)
                            } else {
                                self.emit(I::Const(c - Interval::point(1.0)))
                            };
                            let p = self.emit(I::Pow(a, lower));
                            let f = self.emit(I::Mul(b, p));
                            Some(self.emit(I::Mul(f, da)))
                        }
                    },
                    // (a^b)' = (a^b·ln a)·b' + (b·a^(b−1))·a': the power rule's factor, not
                    // a^b·b/a, whose a^b and a vary together (up to 25× wider over the tests'
                    // boxes for `(2 + y)^(1 + 0.5*x)`).
                    None => {
                        let l = match d[b] {
                            None => None,
                            Some(db) => {
                                let ln = self.emit(I::Call(IntervalFun::Ln, a));
                                let f = self.emit(I::Mul(i, ln));
                                Some(self.emit(I::Mul(f, db)))
                            }
                        };
                        let r = match d[a] {
                            None => None,
                            Some(da) => {
                                let one = self.point(1.0);
                                let lower = self.emit(I::Sub(b, one));
                                let p = self.emit(I::Pow(a, lower));
                                let f = self.emit(I::Mul(b, p));
                                Some(self.emit(I::Mul(f, da)))
                            }
                        };
                        self.add(l, r)
                    }
                },
                I::Call(f, a) => match d[a] {
                    None => None,
                    Some(da) => {
                        let f = match f {
                            // √a' = 0.5/√a.
                            IntervalFun::Sqrt => {
                                let half = self.point(0.5);
                                self.emit(I::Div(half, i))
                            }
                            IntervalFun::Exp => i,
                            IntervalFun::Ln => {
                                let one = self.point(1.0);
                                self.emit(I::Div(one, a))
                            }
                            IntervalFun::Sin => self.emit(I::Call(IntervalFun::Cos, a)),
                            IntervalFun::Cos => {
                                let s = self.emit(I::Call(IntervalFun::Sin, a));
                                self.emit(I::Neg(s))
                            }
                            // tan' = 1 + tan².
                            IntervalFun::Tan => {
                                let one = self.point(1.0);
                                let t2 = self.emit(I::Sqr(i));
                                self.emit(I::Add(one, t2))
                            }
                        };
                        Some(self.emit(I::Mul(f, da)))
                    }
                },
            };
            d.push(di);
        }
        d
    }

    /// The code that computes `outputs`, without the instructions none of them reads.
    fn tape(&self, outputs: &[Option<usize>]) -> IntervalTape {
        let mut live = vec![false; self.ins.len()];
        for &o in outputs.iter().flatten() {
            live[o] = true;
        }
        for i in (0..self.ins.len()).rev() {
            if live[i] {
                for a in self.ins[i].operands().into_iter().flatten() {
                    live[a] = true;
                }
            }
        }
        let mut map = vec![usize::MAX; self.ins.len()];
        let mut ins = Vec::new();
        for (i, x) in self.ins.iter().enumerate() {
            if live[i] {
                map[i] = ins.len();
                ins.push(x.renumbered(&map));
            }
        }
        IntervalTape {
            ins,
            outputs: outputs.iter().map(|o| o.map(|s| map[s])).collect(),
        }
    }
}

/// The interval forms of an [`Expression`] in `dim` coordinates.
#[derive(Clone, Debug, PartialEq)]
struct IntervalForms {
    /// `g` and `∂g/∂x_k` (`k < dim`), for the box centre.
    first: IntervalTape,
    /// `g`, `∂g/∂x_k` and `∂²g/∂x_k∂x_l` (`k ≤ l`, row by row), for the box.
    second: IntervalTape,
}

/// Index of `∂²g/∂x_k∂x_l` among [`IntervalForms::second`]'s results.
fn hessian_index(dim: usize, k: usize, l: usize) -> usize {
    let (k, l) = (k.min(l), k.max(l));
    1 + dim + k * dim - k * (k + 1) / 2 + l
}

impl IntervalForms {
    /// `None` when `tree` uses a function without an interval extension.
    fn compile(tree: &Node, dim: usize) -> Option<IntervalForms> {
        let mut b = IntervalBuilder::default();
        let root = b.push(tree, dim)?;
        let n0 = b.ins.len();
        let gradient: Vec<Option<usize>> = (0..dim).map(|k| b.derivatives(n0, k)[root]).collect();
        let n1 = b.ins.len();
        let second: Vec<Vec<Option<usize>>> = (0..dim).map(|l| b.derivatives(n1, l)).collect();
        let mut first_outputs = vec![Some(root)];
        first_outputs.extend(&gradient);
        let mut second_outputs = first_outputs.clone();
        for k in 0..dim {
            for row in &second[k..] {
                second_outputs.push(gradient[k].and_then(|g| row[g]));
            }
        }
        debug_assert_eq!(
            second_outputs.len(),
            hessian_index(dim, dim - 1, dim - 1) + 1
        );
        Some(IntervalForms {
            first: b.tape(&first_outputs),
            second: b.tape(&second_outputs),
        })
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
/// parses to the same tree in both number types: until session 26 the interval forms, now the
/// tests' reference for the widths of [`IntervalForms`].
#[cfg(test)]
#[derive(Clone, Debug)]
struct IntervalOps;

#[cfg(test)]
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
#[cfg(test)]
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

#[cfg(test)]
type IntervalEx = FlatEx<Interval, IntervalOps, literal::DecimalMatcher>;

/// One compiled expression and, for each of its variables (in `exmex`'s order), the coordinate it
/// reads.
#[cfg(test)]
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
    /// `g`, `∇g` and the second partials over intervals (for the mean-value forms), or `None`
    /// when a function has no interval extension.
    interval: Option<IntervalForms>,
    /// `g` and `∇g` as evaluated ([`Tape`]).
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
        // `exmex` reads the text once more only to check it (its messages on names are kept).
        let ex = exmex::parse::<f64>(&exmex_text).map_err(|e| err(e.to_string()))?;
        slots_of(ex.var_names(), dim, text)?;
        // A function without an interval extension (e.g. `atan`) still fits, only without the
        // Plantinga–Vegter test.
        let interval = IntervalForms::compile(&tree, dim);
        let tape = Tape::compile(&tree, dim)
            .ok_or_else(|| err("a name that is neither a coordinate nor a constant".to_string()))?;
        Ok(Expression {
            text: text.to_string(),
            dim,
            tape,
            interval,
        })
    }

    /// The source text.
    pub fn text(&self) -> &str {
        &self.text
    }

    /// Whether interval enclosures are available (every function used has an interval version).
    pub fn has_interval_extension(&self) -> bool {
        self.interval.is_some()
    }
}

#[cfg(test)]
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
        let forms = self.interval.as_ref()?;
        let n = self.dim;
        let (mut boxes, mut centre, mut offsets) =
            ([Interval::default(); 3], [0.0; 3], [Interval::default(); 3]);
        for k in 0..n {
            boxes[k] = Interval::new(lo[k], hi[k]);
            centre[k] = 0.5 * (lo[k] + hi[k]);
            offsets[k] = boxes[k] - Interval::point(centre[k]);
        }
        let centre = centre.map(Interval::point);
        // Over the box: g, ∇g, then the second partials (at most 1 + 3 + 6).
        let mut over = [Interval::default(); 10];
        forms.second.eval(&boxes[..n], &mut over);
        // At the centre: g and ∇g.
        let mut at = [Interval::default(); 4];
        forms.first.eval(&centre[..n], &mut at);
        let natural = &over[1..=n];
        let mut v = at[0];
        for (g, o) in natural.iter().zip(&offsets) {
            v = v + *g * *o;
        }
        let value = over[0].intersect(v);
        let gradient = (0..n)
            .map(|k| {
                let mut g = at[1 + k];
                for (l, o) in offsets[..n].iter().enumerate() {
                    let h = hessian_index(n, k, l);
                    // A second partial that is exactly 0 adds nothing (not even a rounding).
                    if forms.second.outputs[h].is_some() {
                        g = g + over[h] * *o;
                    }
                }
                natural[k].intersect(g)
            })
            .collect();
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
            ("(2 + y)^(1 + 0.5*x) + tan(0.3*y) - -x + exp(x)/cos(y)", 2),
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
            // Batches shorter than, as long as and just longer than a group of lanes, then all.
            for m in [1, 2, LANES - 1, LANES, LANES + 1] {
                e.gradient_each(&points[..m], &mut out);
                assert_eq!(out.len(), m, "{text}");
                for (p, (v, g)) in points.iter().zip(&out) {
                    let mut g0 = [0.0; 3];
                    let v0 = e.gradient(&p[..dim], &mut g0[..dim]);
                    assert_eq!(v.to_bits(), v0.to_bits(), "{text} at {p:?}");
                    assert_eq!(g.map(f64::to_bits), g0.map(f64::to_bits), "{text} at {p:?}");
                }
            }
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

    /// A closed form for the interval tests: `g`, `∇g` and the Hessian at a point, written by
    /// hand from the text (not by the code under test).
    type ClosedForm = fn(&[f64; 3]) -> (f64, [f64; 3], [[f64; 3]; 3]);

    /// Expressions with their closed forms: products and powers (the torus), quotients by small
    /// constants, integer and real powers of sums, quotients of variables, every function with an
    /// interval extension, a variable exponent and a constant base.
    fn closed_forms() -> Vec<(&'static str, ClosedForm)> {
        vec![
            (
                "(x^2 + y^2 + z^2 + 0.36 - 0.0625)^2 - 1.44*(x^2 + y^2)",
                |p| {
                    let [x, y, z] = *p;
                    let u = x * x + y * y + z * z + 0.36 - 0.0625;
                    let g = u * u - 1.44 * (x * x + y * y);
                    let grad = [4.0 * u * x - 2.88 * x, 4.0 * u * y - 2.88 * y, 4.0 * u * z];
                    let h =
                        |a: f64, b: f64, same: bool| 8.0 * a * b + if same { 4.0 * u } else { 0.0 };
                    let hess = [
                        [h(x, x, true) - 2.88, h(x, y, false), h(x, z, false)],
                        [h(y, x, false), h(y, y, true) - 2.88, h(y, z, false)],
                        [h(z, x, false), h(z, y, false), h(z, z, true)],
                    ];
                    (g, grad, hess)
                },
            ),
            ("x^2/0.81 + y^2/0.09 + z^2/0.0036 - 1", |p| {
                let [x, y, z] = *p;
                let g = x * x / 0.81 + y * y / 0.09 + z * z / 0.0036 - 1.0;
                let grad = [2.0 * x / 0.81, 2.0 * y / 0.09, 2.0 * z / 0.0036];
                let hess = [
                    [2.0 / 0.81, 0.0, 0.0],
                    [0.0, 2.0 / 0.09, 0.0],
                    [0.0, 0.0, 2.0 / 0.0036],
                ];
                (g, grad, hess)
            }),
            ("(x - 0.3)^3/(1 + y^2) - z^4 + x/(2 + z)", |p| {
                let [x, y, z] = *p;
                let (a, q, w) = (x - 0.3, 1.0 + y * y, 2.0 + z);
                let g = a.powi(3) / q - z.powi(4) + x / w;
                let grad = [
                    3.0 * a * a / q + 1.0 / w,
                    -2.0 * y * a.powi(3) / (q * q),
                    -4.0 * z.powi(3) - x / (w * w),
                ];
                let hxy = -6.0 * y * a * a / (q * q);
                let hxz = -1.0 / (w * w);
                let hyy = a.powi(3) * (8.0 * y * y / q.powi(3) - 2.0 / (q * q));
                let hess = [
                    [6.0 * a / q, hxy, hxz],
                    [hxy, hyy, 0.0],
                    [hxz, 0.0, -12.0 * z * z + 2.0 * x / w.powi(3)],
                ];
                (g, grad, hess)
            }),
            (
                "sqrt(1.5 + x*y) + exp(-x)*cos(y) - ln(2 + z^2) + sin(x*z) + tan(0.3*y)",
                |p| {
                    let [x, y, z] = *p;
                    let s = (1.5 + x * y).sqrt();
                    let (e, c, sn) = ((-x).exp(), y.cos(), y.sin());
                    let l = 2.0 + z * z;
                    let (sxz, cxz) = ((x * z).sin(), (x * z).cos());
                    let t = (0.3 * y).tan();
                    let g = s + e * c - l.ln() + sxz + t;
                    let grad = [
                        y / (2.0 * s) - e * c + z * cxz,
                        x / (2.0 * s) - e * sn + 0.3 * (1.0 + t * t),
                        -2.0 * z / l + x * cxz,
                    ];
                    let s3 = 4.0 * s * s * s;
                    let hxy = 1.0 / (2.0 * s) - x * y / s3 + e * sn;
                    let hxz = cxz - x * z * sxz;
                    let hess = [
                        [-y * y / s3 + e * c - z * z * sxz, hxy, hxz],
                        [hxy, -x * x / s3 - e * c + 0.18 * t * (1.0 + t * t), 0.0],
                        [hxz, 0.0, (2.0 * z * z - 4.0) / (l * l) - x * x * sxz],
                    ];
                    (g, grad, hess)
                },
            ),
            ("(2 + y)^(1 + 0.5*x) - 2^-z", |p| {
                let [x, y, z] = *p;
                let (b, e) = (2.0 + y, 1.0 + 0.5 * x);
                let v = b.powf(e);
                let l = b.ln();
                let w = 2f64.powf(-z);
                let l2 = std::f64::consts::LN_2;
                let g = v - w;
                let grad = [0.5 * l * v, e * v / b, l2 * w];
                let hxy = 0.5 * v / b + 0.5 * l * e * v / b;
                let hess = [
                    [0.25 * l * l * v, hxy, 0.0],
                    [hxy, e * (e - 1.0) * v / (b * b), 0.0],
                    [0.0, 0.0, -l2 * l2 * w],
                ];
                (g, grad, hess)
            }),
        ]
    }

    /// Random boxes inside `[-0.9, 0.9]³` of sides up to 0.3 (some degenerate), from `seed`.
    fn random_box(rng: &mut u64) -> ([f64; 3], [f64; 3]) {
        let mut next = || {
            *rng ^= *rng << 13;
            *rng ^= *rng >> 7;
            *rng ^= *rng << 17;
            (*rng >> 11) as f64 / (1u64 << 53) as f64
        };
        let (mut lo, mut hi) = ([0.0; 3], [0.0; 3]);
        for k in 0..3 {
            let side = if next() < 0.1 {
                0.0
            } else {
                0.3 * next().powi(2)
            };
            lo[k] = -0.9 + (1.8 - side) * next();
            hi[k] = lo[k] + side;
        }
        (lo, hi)
    }

    /// The enclosures of `g`, `∇g` (natural ∩ mean-value) and of each second partial (the
    /// tape's own) hold the closed forms at points of random boxes: corners, centre and random
    /// points. Ground truth is the hand-written closed form in `f64`, allowed a relative slack of
    /// 10⁻¹² for its own rounding.
    #[test]
    fn interval_forms_enclose_closed_forms_over_random_boxes() {
        let slack = |v: f64| 1e-12 * (1.0 + v.abs());
        let holds = |iv: Interval, v: f64| iv.lo - slack(v) <= v && v <= iv.hi + slack(v);
        let mut rng: u64 = 0x9e37_79b9_7f4a_7c15;
        for (text, truth) in closed_forms() {
            let e = Expression::parse(text, 3).unwrap();
            let forms = e.interval.as_ref().expect(text);
            let mut finite = 0;
            for _ in 0..400 {
                let (lo, hi) = random_box(&mut rng);
                let en = e.enclose(&lo, &hi).unwrap();
                let boxes: Vec<Interval> = (0..3).map(|k| Interval::new(lo[k], hi[k])).collect();
                let mut over = [Interval::default(); 10];
                forms.second.eval(&boxes, &mut over);
                if en.value.width().is_finite() && en.gradient.iter().all(|g| g.width().is_finite())
                {
                    finite += 1;
                }
                for s in 0..20 {
                    let t: [f64; 3] = match s {
                        0..=7 => [0, 1, 2].map(|k| ((s >> k) & 1) as f64),
                        8 => [0.5; 3],
                        _ => [(); 3].map(|_| random_box(&mut rng).0[0] / 1.8 + 0.5),
                    };
                    let p = [0, 1, 2].map(|k| (lo[k] + t[k] * (hi[k] - lo[k])).min(hi[k]));
                    let (g, grad, hess) = truth(&p);
                    assert!(holds(en.value, g), "{text} g={g} {:?} at {p:?}", en.value);
                    for k in 0..3 {
                        let iv = en.gradient[k];
                        assert!(
                            holds(iv, grad[k]),
                            "{text} d{k}={} {iv:?} at {p:?}",
                            grad[k]
                        );
                        for l in 0..3 {
                            let iv = over[hessian_index(3, k, l)];
                            let h = hess[k][l];
                            assert!(holds(iv, h), "{text} d{k}d{l}={h} {iv:?} at {p:?}");
                        }
                    }
                }
            }
            // Not vacuous: the enclosures are finite on most boxes.
            assert!(finite > 300, "{text}: {finite}");
        }
    }

    /// Where an operation is undefined or overflows, the enclosure is the whole line (or
    /// unbounded on that side), never narrower; and where the value is bounded, tight enough to
    /// exclude 0 away from the zero set.
    #[test]
    fn undefined_and_overflowing_enclosures_are_unbounded() {
        let whole = |text: &str, lo: &[f64], hi: &[f64]| {
            let e = Expression::parse(text, lo.len()).unwrap();
            e.enclose(lo, hi).unwrap()
        };
        for (text, lo, hi) in [
            ("sqrt(x) + y", [-1.0, 0.0], [1.0, 1.0]),
            ("ln(x) + y", [-1.0, 0.0], [1.0, 1.0]),
            ("1/x + y", [-1.0, 0.0], [1.0, 1.0]),
            ("x^0.5 + y", [-1.0, 0.0], [1.0, 1.0]),
            ("tan(x) + y", [1.0, 0.0], [2.0, 1.0]),
        ] {
            let en = whole(text, &lo, &hi);
            assert_eq!(en.value, Interval::ENTIRE, "{text}");
            // tan' = 1 + tan² ≥ 1 holds wherever tan is defined: [1, ∞) is an enclosure.
            let g = en.gradient[0];
            assert!(g.hi == f64::INFINITY && g.lo <= 1.0, "{text}: {g:?}");
        }
        let en = whole("exp(x) - y", &[700.0, 0.0], &[720.0, 1.0]);
        assert_eq!(en.value.hi, f64::INFINITY);
        assert_eq!(en.gradient[0].hi, f64::INFINITY);
        assert!(en.gradient[1].contains(-1.0));
        let en = whole("x^2 + y^2 - 1", &[2.0, 2.0], &[2.5, 2.5]);
        assert!(en.value.lo > 6.9 && en.value.hi < 11.6, "{:?}", en.value);
    }

    /// Literals are exact in the interval forms only when they are integers (every double below
    /// 10¹⁵ is); an exact exponent keeps `Interval::pow`'s repeated products.
    #[test]
    fn only_integer_literals_are_exact() {
        for (text, exact) in [
            ("2", true),
            ("2.000", true),
            ("1e3", true),
            ("1.5e1", true),
            ("0", true),
            ("0.000e7", true),
            ("999999999999999", true),
            ("1e15", false),
            ("0.5", false),
            ("1e-3", false),
            ("12e-1", false),
            ("2.0000000000000001", false),
            ("1e99999999999999999999", false),
        ] {
            assert_eq!(literal_is_exact(text), exact, "{text}");
        }
        // `2.0000000000000001` reads as the double 2 but is not 2: its square's enclosure must
        // hold the real square of the literal, above 4.
        let e = Expression::parse("x*2.0000000000000001", 1).unwrap();
        let v = e.enclose(&[2.0], &[2.0]).unwrap().value;
        assert!(v.lo < 4.0 && v.hi > 4.0, "{v:?}");
        // An exponent folded from integers stays exact: x^(3-1) ≥ 0 over a box around 0, where
        // exp(2·ln x) would be the whole line.
        let e = Expression::parse("x^(3-1) - y", 2).unwrap();
        let en = e.enclose(&[-0.5, 0.0], &[0.5, 0.0]).unwrap();
        assert!(
            en.value.lo >= -1e-300 && en.value.hi <= 0.26,
            "{:?}",
            en.value
        );
    }

    /// The compiled interval forms are never wider than the `exmex` forms they replace (session
    /// 26) but for the rounding of constants: widths of `g` and `∇g` over random boxes.
    #[test]
    fn interval_forms_are_as_tight_as_the_exmex_forms() {
        let mut rng: u64 = 0x2545_f491_4f6c_dd1d;
        for (text, _) in closed_forms() {
            let e = Expression::parse(text, 3).unwrap();
            let reference = ExmexForms::parse(text);
            let (mut worst, mut sum, mut count) = (0.0f64, 0.0, 0);
            for _ in 0..400 {
                let (lo, hi) = random_box(&mut rng);
                let new = e.enclose(&lo, &hi).unwrap();
                let old = reference.enclose(&lo, &hi);
                let pairs = std::iter::once((new.value, old.value)).chain(
                    new.gradient
                        .iter()
                        .copied()
                        .zip(old.gradient.iter().copied()),
                );
                for (a, b) in pairs {
                    // Constants are rounded differently (`exmex` folds `ln 2` in `f64` and
                    // widens the double by one rounding, the tape folds it in interval
                    // arithmetic): up to 64 ulps of the magnitude either way.
                    let rounding = 64.0 * f64::EPSILON * b.lo.abs().max(b.hi.abs()).max(1.0);
                    assert!(
                        !b.width().is_finite() || a.width() <= b.width() * (1.0 + 1e-9) + rounding,
                        "{text} over {lo:?}..{hi:?}: {a:?} wider than {b:?}"
                    );
                    if b.width().is_finite() && b.width() > 1e6 * rounding {
                        let ratio = a.width() / b.width();
                        worst = worst.max(ratio);
                        sum += ratio;
                        count += 1;
                    }
                }
            }
            eprintln!(
                "{text}: width new/old worst {worst:.4}, mean {:.4}",
                sum / count as f64
            );
            assert!(
                count > 400 && worst <= 1.0 + 1e-9,
                "{text}: {worst} of {count}"
            );
        }
    }

    /// The interval forms as they were until session 26: `exmex`'s symbolic derivatives, each
    /// re-parsed over [`Interval`] and evaluated by `exmex`.
    struct ExmexForms {
        value: Compiled<IntervalEx>,
        partials: Vec<Option<Compiled<IntervalEx>>>,
        hessian: Vec<Vec<Option<Compiled<IntervalEx>>>>,
    }

    impl ExmexForms {
        fn parse(text: &str) -> ExmexForms {
            let mut t = String::new();
            parse_tree(text).unwrap().to_exmex(&mut t);
            let ex = exmex::parse::<f64>(&t).unwrap();
            let to_interval = |f: &FlatEx<f64>| {
                let ex = IntervalEx::parse(f.unparse()).unwrap();
                let slots = slots_of(ex.var_names(), 3, text).unwrap();
                Compiled { ex, slots }
            };
            let slots = slots_of(ex.var_names(), 3, text).unwrap();
            let mut partials = vec![None; 3];
            let mut hessian = vec![vec![None; 3]; 3];
            for (i, &k) in slots.iter().enumerate() {
                let d = ex.clone().partial(i).unwrap();
                let d_slots = slots_of(d.var_names(), 3, text).unwrap();
                for (j, &l) in d_slots.iter().enumerate() {
                    hessian[k][l] = Some(to_interval(&d.clone().partial(j).unwrap()));
                }
                partials[k] = Some(to_interval(&d));
            }
            ExmexForms {
                value: to_interval(&ex),
                partials,
                hessian,
            }
        }

        /// Session 25's `Expression::enclose`, verbatim but for the names.
        fn enclose(&self, lo: &[f64], hi: &[f64]) -> Enclosure {
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
            let natural: Vec<Interval> = self
                .partials
                .iter()
                .map(|d| partial_over(d, &boxes))
                .collect();
            let mut v = eval_interval(&self.value, &centre);
            for (g, o) in natural.iter().zip(&offsets) {
                v = v + *g * *o;
            }
            let value = eval_interval(&self.value, &boxes).intersect(v);
            let gradient = natural
                .iter()
                .zip(self.partials.iter().zip(&self.hessian))
                .map(|(nat, (d, row))| {
                    let mut g = partial_over(d, &centre);
                    for (hd, o) in row.iter().zip(&offsets) {
                        g = g + partial_over(hd, &boxes) * *o;
                    }
                    nat.intersect(g)
                })
                .collect();
            Enclosure { value, gradient }
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
