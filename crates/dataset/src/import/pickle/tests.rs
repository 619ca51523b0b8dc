use super::*;

// Bytes written by CPython 3.11 `pickle.dumps([[1.5, 2.0], [3]], protocol=4)`.
const NESTED: &[u8] = b"\x80\x04\x95\x20\x00\x00\x00\x00\x00\x00\x00]\x94(]\x94(G?\xf8\x00\x00\x00\x00\x00\x00G@\x00\x00\x00\x00\x00\x00\x00e]\x94K\x03ae.";

#[test]
fn parses_nested_lists() {
    let v = parse(NESTED).unwrap();
    let want = Value::List(vec![
        Value::List(vec![Value::Float(1.5), Value::Float(2.0)]),
        Value::List(vec![Value::Int(3)]),
    ]);
    assert_eq!(v, want);
}

#[test]
fn every_truncation_is_an_error() {
    for cut in 0..NESTED.len() {
        assert!(parse(&NESTED[..cut]).is_err(), "cut at {cut} parsed");
    }
    let file = include_bytes!("testdata/np2_p4.pkl");
    for cut in 0..file.len() {
        assert!(parse(&file[..cut]).is_err(), "cut at {cut} parsed");
    }
}

#[test]
fn refuses_lists_nested_past_the_limit_without_overflowing_the_stack() {
    // `[[[...]]]` a million deep: built by appending each list to the one below it.
    let n = 1_000_000;
    let mut bytes = b"\x80\x02".to_vec();
    bytes.extend(std::iter::repeat_n(b']', n));
    bytes.extend(std::iter::repeat_n(b'a', n - 1));
    bytes.push(b'.');
    let err = parse(&bytes).unwrap_err();
    assert!(err.contains("more than 32 deep"), "{err}");
    // At the limit it parses.
    let d = MAX_DEPTH as usize;
    let mut ok = b"\x80\x02".to_vec();
    ok.extend(std::iter::repeat_n(b']', d));
    ok.extend(std::iter::repeat_n(b'a', d - 1));
    ok.push(b'.');
    assert!(parse(&ok).is_ok());
}

#[test]
fn refuses_names_outside_numpy_arrays() {
    // `pickle.dumps(print)`: STACK_GLOBAL of builtins.print.
    let err =
        parse(b"\x80\x04\x95\x00\x00\x00\x00\x00\x00\x00\x00\x8c\x08builtins\x8c\x05print\x93.")
            .unwrap_err();
    assert!(
        err.contains("builtins.print") && err.contains("refused"),
        "{err}"
    );
    // Protocol 2's GLOBAL of os.system, called: refused at the name, before any call.
    let err = parse(b"\x80\x02cos\nsystem\nX\x02\x00\x00\x00ls\x85R.").unwrap_err();
    assert!(err.contains("os.system"), "{err}");
}

#[test]
fn refuses_a_list_changed_after_it_was_stored_when_referred_to_again() {
    // l = []; memo 0 = l; l.append(1); then (l, memo 0): Python would share l.
    let bytes = b"\x80\x04]\x94K\x01ah\x00\x86.";
    let err = parse(bytes).unwrap_err();
    assert!(err.contains("changed after"), "{err}");
}

#[test]
fn bounds_the_copies_a_small_file_can_make() {
    // A tuple of 1000 ints, then tuples of 1000 references to the one before, four levels:
    // 10^15 values as copies, from a file of a few kilobytes.
    let mut b = b"\x80\x04(".to_vec();
    b.extend(std::iter::repeat_n(b"K\x01".as_slice(), 1000).flatten());
    b.extend(b"t\x94");
    for level in 0..4u8 {
        b.push(b'(');
        b.extend(std::iter::repeat_n([b'h', level], 1000).flatten());
        b.extend(b"t\x94");
    }
    b.push(b'.');
    let err = parse(&b).unwrap_err();
    assert!(err.contains("more than 50000000 values"), "{err}");
}

fn array<'a>(v: &'a Value, key: &str) -> &'a NdArray {
    match v.get(key) {
        Some(Value::Array(a)) => a,
        other => panic!("{key}: {other:?}"),
    }
}

/// The values `testdata/make.py` writes, whichever numpy and protocol wrote them.
fn check_sample(v: &Value, name: &str) {
    let f4 = array(v, "f4");
    assert_eq!(
        (f4.dtype, f4.shape.as_slice()),
        (Dtype::Float(4), &[2, 3][..]),
        "{name}"
    );
    assert_eq!(f4.to_f64(), [0.0, 0.25, 0.5, 0.75, 1.0, 1.25], "{name}");
    assert_eq!(
        array(v, "f4_again").to_f64(),
        [1.0, 1.25, 1.5, 1.75, 2.0, 2.25],
        "{name}"
    );
    let f = array(v, "f8_fortran");
    assert_eq!(f.shape, [2, 3], "{name}");
    assert_eq!(
        f.to_f64(),
        [0.0, 1.0, 2.0, 3.0, 4.0, 5.0],
        "{name}: C order"
    );
    assert_eq!(array(v, "big_endian").to_f64(), [1.5, -2.25], "{name}");
    let b = array(v, "b1");
    assert_eq!(b.dtype, Dtype::Bool, "{name}");
    assert_eq!(
        b.to_bool(),
        [true, false, true, false, false, true],
        "{name}"
    );
    assert_eq!(array(v, "i8").to_f64(), [-3.0, 0.0, 7.0], "{name}");
    assert_eq!(array(v, "u2").to_f64(), [1.0, 65535.0], "{name}");
    let s = array(v, "scalar");
    assert!(s.shape.is_empty(), "{name}");
    assert_eq!(s.to_f64(), [2.5], "{name}");
    let e = array(v, "empty");
    assert_eq!(
        (e.shape.as_slice(), e.is_empty()),
        (&[0, 3][..], true),
        "{name}"
    );
    let plain = Value::List(vec![
        Value::Int(1),
        Value::Float(2.5),
        Value::Str("text".into()),
        Value::Tuple(vec![Value::None, Value::Bool(true), Value::Bool(false)]),
        Value::Dict(vec![(Value::Str("k".into()), Value::Int(-70000))]),
    ]);
    assert_eq!(v.get("plain"), Some(&plain), "{name}");
}

#[test]
fn reads_numpy_arrays_of_numpy_1_and_2_in_protocols_2_to_5() {
    let files: [(&str, &[u8]); 5] = [
        ("np1_p2", include_bytes!("testdata/np1_p2.pkl")),
        ("np1_p4", include_bytes!("testdata/np1_p4.pkl")),
        ("np2_p2", include_bytes!("testdata/np2_p2.pkl")),
        ("np2_p4", include_bytes!("testdata/np2_p4.pkl")),
        ("np2_p5", include_bytes!("testdata/np2_p5.pkl")),
    ];
    for (name, bytes) in files {
        let v = parse(bytes).unwrap_or_else(|e| panic!("{name}: {e}"));
        check_sample(&v, name);
    }
}

#[test]
fn refuses_an_array_whose_bytes_do_not_match_its_shape() {
    // A float32 array of shape (2, 3) with one byte missing: the 24-byte SHORT_BINBYTES of
    // np2_p4's first array is rewritten as 23 bytes by hand.
    let file = include_bytes!("testdata/np2_p4.pkl").to_vec();
    let at = file
        .windows(2)
        .position(|w| w == [b'C', 24])
        .expect("the first array's data");
    let mut bad = file[..at].to_vec();
    bad.extend([b'C', 23]);
    bad.extend(&file[at + 2..at + 2 + 23]);
    bad.extend(&file[at + 2 + 24..]);
    let err = parse(&bad).unwrap_err();
    assert!(err.contains("holds 23 bytes"), "{err}");
}
