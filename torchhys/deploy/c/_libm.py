"""The libm-free ``exp``, ``sigmoid`` and ``tanh`` of the generated C (the bodies of the
writer's helpers, :meth:`torchhys.deploy.c._writer.Writer.helper`): branch-free, so that a
loop of them vectorizes at ``-O2`` (a loop of libm calls does not); NaN, overflow and
underflow as libm's."""

# exp of a double without libm, branch-free so that a loop of it vectorizes (a libm call in
# a loop does not): x = k ln2 + r, |r| <= ln2 / 2, with a two-constant Cody-Waite split
# (fdlibm's ln2 hi and lo; k ln2hi exact for |k| < 2^21); exp(r) fdlibm's rational form
# 1 + r + r c / (2 - c), c = r - r^2 P(r^2) (P of degree 4: error < 2^-59 on the interval); times
# 2^k as two exact factors 2^floor(k/2) and 2^ceil(k/2) built in the exponent bits, so that
# a subnormal result is rounded once. k is read from the bits of x log2e + 1.5 2^52 (no
# conversion of a float to an integer: none is undefined for NaN), and k as a double is the
# double of those bits with the exponent of 2^52, less 1.5 2^52 (exact): not the sum less
# 1.5 2^52, which -fassociative-math (in -ffast-math) folds to x log2e, unrounded.
# |x| > 746 is replaced by +-746 (exp: inf, resp. 0, as libm); a NaN goes through as NaN;
# the select uses fabs and copysign (GCC does not if-convert a clamp to two constants under
# -ftrapping-math). Within 1 ulp of glibc's exp (tests/test_exp_c.py).
_EXP_DOUBLE = """double kd, hi, lo, r, t, c, p, s1, s2;
    uint64_t bits, kb;
    x = (fabs(x) > 746.0) ? copysign(746.0, x) : x;
    kd = x * 1.4426950408889634 + 6755399441055744.0;
    memcpy(&bits, &kd, sizeof bits);
    kb = bits & UINT64_C(0xFFFFFFFFFFFFF); /* k + 2^51 */
    bits = kb | UINT64_C(0x4330000000000000); /* 1.5 2^52 + k */
    memcpy(&kd, &bits, sizeof kd);
    kd -= 6755399441055744.0;
    hi = x - kd * 6.93147180369123816490e-01;
    lo = kd * 1.90821492927058770002e-10;
    r = hi - lo;
    t = r * r;
    c = r - t * (1.66666666666666019037e-01 + t * (-2.77777777770155933842e-03
        + t * (6.61375632143793436117e-05 + t * (-1.65339022054652515390e-06
        + t * 4.13813679705723846039e-08))));
    p = 1.0 - ((lo - (r * c) / (2.0 - c)) - hi);
    bits = ((kb >> 1) - (UINT64_C(1) << 50) + 1023) << 52;
    memcpy(&s1, &bits, sizeof s1);
    bits = ((kb - (kb >> 1)) - (UINT64_C(1) << 50) + 1023) << 52;
    memcpy(&s2, &bits, sizeof s2);
    return p * s1 * s2;"""

# sigmoid(x) = 1 / (1 + exp(-x)) with one division: exp(-x)'s reduction as above, and
# exp(r) = 1 + r + r c / (2 - c) = (2 + 2r - c) / (2 - c) (halved, so that 2^k times the
# numerator stays finite where exp does), sigmoid = d / (d + 2^k n). Within 4 ulp of
# 1 / (1 + exp(-x)) with libm's exp; 0, 1 and NaN where that gives them.
_SIGMOID_DOUBLE = (
    _EXP_DOUBLE.replace("double kd, hi, lo, r, t, c, p, s1, s2;",
                        "double kd, hi, lo, r, t, c, d, n, s1, s2;")
    .replace("    x = (fabs(x) > 746.0)", "    x = -x;\n    x = (fabs(x) > 746.0)")
    .replace("    p = 1.0 - ((lo - (r * c) / (2.0 - c)) - hi);",
             "    d = 1.0 - 0.5 * c;\n    n = (1.0 + r) - 0.5 * c;")
    .replace("    return p * s1 * s2;", "    return d / (d + n * s1 * s2);"))

# tanh of a double without libm (a loop of it vectorizes, as the exp's): tanh |x| =
# e / (e + 2), e = expm1(2 |x|), with the exp's reduction of y = 2 |x| (k >= 0) and its
# rational form: expm1(r) = hi - (lo - r c / (2 - c)) (no cancellation: r, not 1 + r, is
# formed), expm1(y) = 2^k expm1(r) + (2^k - 1). |x| > 20 is replaced by +-20 (tanh rounds to
# 1 from 19.1 on: 2^k stays finite; GCC if-converts this one select of the argument, as the
# exp's clamp, but no second one); the sign is copied from x (tanh is odd: -0 stays -0); a
# NaN goes through as NaN; a tiny x gives x within 2 ulp (e / (e + 2) rounds twice). Within
# 3 ulp of glibc's tanh and 2 of torch's (tests/test_tanh_c.py).
_TANH_DOUBLE = """double a, kd, hi, lo, r, t, c, s, e;
    uint64_t bits, kb;
    x = (fabs(x) > 20.0) ? copysign(20.0, x) : x;
    a = fabs(x);
    a = a + a;
    kd = a * 1.4426950408889634 + 6755399441055744.0;
    memcpy(&bits, &kd, sizeof bits);
    kb = bits & UINT64_C(0xFFFFFFFFFFFFF); /* k + 2^51 */
    bits = kb | UINT64_C(0x4330000000000000); /* 1.5 2^52 + k */
    memcpy(&kd, &bits, sizeof kd);
    kd -= 6755399441055744.0;
    hi = a - kd * 6.93147180369123816490e-01;
    lo = kd * 1.90821492927058770002e-10;
    r = hi - lo;
    t = r * r;
    c = r - t * (1.66666666666666019037e-01 + t * (-2.77777777770155933842e-03
        + t * (6.61375632143793436117e-05 + t * (-1.65339022054652515390e-06
        + t * 4.13813679705723846039e-08))));
    bits = ((kb - (UINT64_C(1) << 51) + 1023) & UINT64_C(0x7FF)) << 52;
    memcpy(&s, &bits, sizeof s);
    e = s * (hi - (lo - (r * c) / (2.0 - c))) + (s - 1.0);
    return copysign(e / (e + 2.0), x);"""

# the exp and the tanh of a float, in float arithmetic (uint32_t bits: no mixed element
# widths): fdlibm's expf constants (ln2 hi and lo, the same P), |x| > 104 replaced by +-104
# (expf: inf, resp. 0) in the exp, |x| > 10 by +-10 in the tanh (tanhf rounds to 1 from
# 9.01 on). Within 1 ulp of glibc's expf and 4 of tanhf (tests/test_libm_float_c.py). The
# float32 sigmoid is 1 / (1 + exp(-x)) with this exp (one division in the sigmoid's way, as
# the double's, would be 5 ulp from it: more than a float32 network's bound allows).
_EXP_FLOAT = """float kd, hi, lo, r, t, c, p, s1, s2;
    uint32_t bits, kb;
    x = (fabsf(x) > 104.0f) ? copysignf(104.0f, x) : x;
    kd = x * 1.44269502f + 12582912.0f;
    memcpy(&bits, &kd, sizeof bits);
    kb = bits & UINT32_C(0x7FFFFF); /* k + 2^22 */
    bits = kb | UINT32_C(0x4B000000); /* 1.5 2^23 + k */
    memcpy(&kd, &bits, sizeof kd);
    kd -= 12582912.0f;
    hi = x - kd * 6.9314575195e-01f;
    lo = kd * 1.4286067653e-06f;
    r = hi - lo;
    t = r * r;
    c = r - t * (1.6666667163e-01f + t * (-2.7777778450e-03f
        + t * (6.6137559770e-05f + t * (-1.6533901999e-06f
        + t * 4.1381369442e-08f))));
    p = 1.0f - ((lo - (r * c) / (2.0f - c)) - hi);
    bits = ((kb >> 1) - (UINT32_C(1) << 21) + 127) << 23;
    memcpy(&s1, &bits, sizeof s1);
    bits = ((kb - (kb >> 1)) - (UINT32_C(1) << 21) + 127) << 23;
    memcpy(&s2, &bits, sizeof s2);
    return p * s1 * s2;"""

_TANH_FLOAT = """float a, kd, hi, lo, r, t, c, s, e;
    uint32_t bits, kb;
    x = (fabsf(x) > 10.0f) ? copysignf(10.0f, x) : x;
    a = fabsf(x);
    a = a + a;
    kd = a * 1.44269502f + 12582912.0f;
    memcpy(&bits, &kd, sizeof bits);
    kb = bits & UINT32_C(0x7FFFFF); /* k + 2^22 */
    bits = kb | UINT32_C(0x4B000000); /* 1.5 2^23 + k */
    memcpy(&kd, &bits, sizeof kd);
    kd -= 12582912.0f;
    hi = a - kd * 6.9314575195e-01f;
    lo = kd * 1.4286067653e-06f;
    r = hi - lo;
    t = r * r;
    c = r - t * (1.6666667163e-01f + t * (-2.7777778450e-03f
        + t * (6.6137559770e-05f + t * (-1.6533901999e-06f
        + t * 4.1381369442e-08f))));
    bits = ((kb - (UINT32_C(1) << 22) + 127) & UINT32_C(0xFF)) << 23;
    memcpy(&s, &bits, sizeof s);
    e = s * (hi - (lo - (r * c) / (2.0f - c))) + (s - 1.0f);
    return copysignf(e / (e + 2.0f), x);"""

#: the libm-free helpers (``x`` their argument), by C type
LIBM_FREE = {"double": {"exp": _EXP_DOUBLE, "sigmoid": _SIGMOID_DOUBLE, "tanh": _TANH_DOUBLE},
             "float": {"exp": _EXP_FLOAT, "tanh": _TANH_FLOAT}}
