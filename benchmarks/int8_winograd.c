/* Prototype of an exact integer Winograd F(2x2, 3x3) for a uint8 3x3, stride-1, pad-1 convolution
   (benchmarks/int8_winograd.py measures it against NNCG's direct int8 kernel of the same layer).

   Geometry at compile time: -DSIZE (output = input side), -DCI, -DCO, -DZX (the input's zero point),
   -DZY (the output's). Channels last, as NNCG's int8 kernels. Per tile row:
     1. V = B^T (x - ZX) B in int16 (|V| <= 4 * 255), 8 (ssse3) or 16 (avx2) input channels a vector;
     2. 16 GEMMs M[e] = sum_ci V[e][ci] * U'[e][ci][co] with pmaddwd on input-channel pairs, U' = G' g G'^T,
        G' = 2G (integer, |U'| <= 9 * 128), register-blocked 2 tiles x 4 vectors of output channels;
     3. Y' = A^T M A + 4 b = 4 (b + sum (x - ZX) w) exactly, requantised with the multiplier m / 4:
        float32(4 acc) * (m / 4) is float32(acc) * m to the bit (scaling by 4 is exact in float32).
   Exits 1 unless every output equals the scalar direct reference's (the same requantisation). */
#include <immintrin.h>
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#ifdef __AVX2__
#define LANES 8
typedef __m256i VI;
typedef __m256 VF;
#define ADD32 _mm256_add_epi32
#define SUB32 _mm256_sub_epi32
#define ADD16 _mm256_add_epi16
#define SUB16 _mm256_sub_epi16
#define MADD _mm256_madd_epi16
#define SET1 _mm256_set1_epi32
#define SET1_16 _mm256_set1_epi16
#define LOAD(p) _mm256_loadu_si256((const VI *)(p))
#define STORE(p, v) _mm256_storeu_si256((VI *)(p), v)
#define ZERO _mm256_setzero_si256()
#define LOAD_U8_AS_16(p) _mm256_cvtepu8_epi16(_mm_loadu_si128((const __m128i *)(p)))
#define CVT _mm256_cvtepi32_ps
#define MULPS _mm256_mul_ps
#define MINPS _mm256_min_ps
#define MAXPS _mm256_max_ps
#define SETPS _mm256_set1_ps
#define LOADPS _mm256_loadu_ps
#define CVTPS _mm256_cvtps_epi32
static void store_u8(uint8_t *p, VI v)
{
    __m128i w = _mm_packs_epi32(_mm256_castsi256_si128(v), _mm256_extracti128_si256(v, 1));
    _mm_storel_epi64((__m128i *)p, _mm_packus_epi16(w, w));
}
#else
#define LANES 4
typedef __m128i VI;
typedef __m128 VF;
#define ADD32 _mm_add_epi32
#define SUB32 _mm_sub_epi32
#define ADD16 _mm_add_epi16
#define SUB16 _mm_sub_epi16
#define MADD _mm_madd_epi16
#define SET1 _mm_set1_epi32
#define SET1_16 _mm_set1_epi16
#define LOAD(p) _mm_loadu_si128((const VI *)(p))
#define STORE(p, v) _mm_storeu_si128((VI *)(p), v)
#define ZERO _mm_setzero_si128()
#define LOAD_U8_AS_16(p) _mm_unpacklo_epi8(_mm_loadl_epi64((const __m128i *)(p)), _mm_setzero_si128())
#define CVT _mm_cvtepi32_ps
#define MULPS _mm_mul_ps
#define MINPS _mm_min_ps
#define MAXPS _mm_max_ps
#define SETPS _mm_set1_ps
#define LOADPS _mm_loadu_ps
#define CVTPS _mm_cvtps_epi32
static void store_u8(uint8_t *p, VI v)
{
    __m128i w = _mm_packs_epi32(v, v);
    int32_t bytes = _mm_cvtsi128_si32(_mm_packus_epi16(w, w));
    memcpy(p, &bytes, 4);
}
#endif

#define PAIRS (2 * LANES) /* int16 lanes: input channels per vector of the input transform */
#if CI % PAIRS || CO % LANES
#error "the prototype takes CI a multiple of 2 * LANES and CO a multiple of LANES"
#endif
#define TILES ((SIZE + 1) / 2)
/* output-channel vectors per GEMM register block: the largest of 4, 3, 2, 1 that divides CO / LANES */
#define BLOCK ((CO / LANES) % 4 == 0 ? 4 : (CO / LANES) % 3 == 0 ? 3 : (CO / LANES) % 2 == 0 ? 2 : 1)

static const int G2[4][3] = {{2, 0, 0}, {1, 1, 1}, {1, -1, 1}, {0, 0, 2}};
static int16_t u_packed[16][CI / 2][CO][2]; /* U' in pmaddwd pairs of input channels */
static int32_t bias4[CO];
static float m4[CO];
static int16_t V[16][TILES + 1][CI];
static int32_t M[16][TILES + 1][CO];

static void prepare(const int8_t *w, const int32_t *b, const float *m)
{
    int co, ci, a, c, i, j;
    for (co = 0; co < CO; co++) {
        bias4[co] = 4 * b[co];
        m4[co] = m[co] / 4.0f;
        for (ci = 0; ci < CI; ci++)
            for (a = 0; a < 4; a++)
                for (c = 0; c < 4; c++) {
                    int s = 0;
                    for (i = 0; i < 3; i++)
                        for (j = 0; j < 3; j++) s += G2[a][i] * w[((co * CI + ci) * 3 + i) * 3 + j] * G2[c][j];
                    u_packed[a * 4 + c][ci / 2][co][ci % 2] = (int16_t)s;
                }
    }
}

/* The transform of one tile's 4x4 patch of input channels ci..ci + PAIRS - 1; `checked` reads the
   patch positions outside the image as 0 (x - ZX of the padding), which interior tiles skip, as NNCG's
   lowering splits its border tiles into loops of their own. */
static inline __attribute__((always_inline)) void transform_patch(const uint8_t *x, int ty, int t, int ci, int checked)
{
    const VI zx = SET1_16((short)ZX);
    VI d[4][4], r[4][4];
    int i, j;
    for (i = 0; i < 4; i++)
        for (j = 0; j < 4; j++) {
            int h = 2 * ty + i - 1, w = 2 * t + j - 1;
            int inside = !checked || (h >= 0 && h < SIZE && w >= 0 && w < SIZE);
            d[i][j] = inside ? SUB16(LOAD_U8_AS_16(&x[(h * SIZE + w) * CI + ci]), zx) : ZERO;
        }
    for (j = 0; j < 4; j++) { /* B^T d */
        r[0][j] = SUB16(d[0][j], d[2][j]);
        r[1][j] = ADD16(d[1][j], d[2][j]);
        r[2][j] = SUB16(d[2][j], d[1][j]);
        r[3][j] = SUB16(d[1][j], d[3][j]);
    }
    for (i = 0; i < 4; i++) { /* (B^T d) B */
        STORE(&V[i * 4 + 0][t][ci], SUB16(r[i][0], r[i][2]));
        STORE(&V[i * 4 + 1][t][ci], ADD16(r[i][1], r[i][2]));
        STORE(&V[i * 4 + 2][t][ci], SUB16(r[i][2], r[i][1]));
        STORE(&V[i * 4 + 3][t][ci], SUB16(r[i][1], r[i][3]));
    }
}

static void input_transform(const uint8_t *x, int ty)
{
    int t, ci, interior_row = ty > 0 && 2 * ty + 2 < SIZE;
    for (t = 0; t < TILES; t++) {
        if (interior_row && t > 0 && 2 * t + 2 < SIZE)
            for (ci = 0; ci < CI; ci += PAIRS) transform_patch(x, ty, t, ci, 0);
        else
            for (ci = 0; ci < CI; ci += PAIRS) transform_patch(x, ty, t, ci, 1);
    }
}

static void gemms(void)
{
    int e, t, co, cp, k;
    for (e = 0; e < 16; e++)
        for (t = 0; t < TILES; t += 2)
            for (co = 0; co < CO; co += BLOCK * LANES) {
                VI acc0[BLOCK], acc1[BLOCK];
                for (k = 0; k < BLOCK; k++) acc0[k] = acc1[k] = ZERO;
                for (cp = 0; cp < CI / 2; cp++) {
                    int32_t p0, p1;
                    VI b0, b1;
                    memcpy(&p0, &V[e][t][2 * cp], 4);
                    memcpy(&p1, &V[e][t + 1][2 * cp], 4);
                    b0 = SET1(p0);
                    b1 = SET1(p1);
                    _Pragma("GCC unroll 4") for (k = 0; k < BLOCK; k++) {
                        VI w = LOAD(&u_packed[e][cp][co + k * LANES][0]);
                        acc0[k] = ADD32(acc0[k], MADD(b0, w));
                        acc1[k] = ADD32(acc1[k], MADD(b1, w));
                    }
                }
                _Pragma("GCC unroll 4") for (k = 0; k < BLOCK; k++) {
                    STORE(&M[e][t][co + k * LANES], acc0[k]);
                    STORE(&M[e][t + 1][co + k * LANES], acc1[k]);
                }
            }
}

static void output_transform(uint8_t *y, int ty)
{
    int t, co, e, i, j;
    for (t = 0; t < TILES; t++)
        for (co = 0; co < CO; co += LANES) {
            VI m[16], s[2][4], bias = LOAD(&bias4[co]);
            VF multiplier = LOADPS(&m4[co]);
            for (e = 0; e < 16; e++) m[e] = LOAD(&M[e][t][co]);
            for (j = 0; j < 4; j++) { /* A^T M */
                s[0][j] = ADD32(ADD32(m[j], m[4 + j]), m[8 + j]);
                s[1][j] = SUB32(SUB32(m[4 + j], m[8 + j]), m[12 + j]);
            }
            for (i = 0; i < 2; i++) { /* (A^T M) A + 4 b, requantised */
                VI out[2];
                out[0] = ADD32(ADD32(ADD32(s[i][0], s[i][1]), s[i][2]), bias);
                out[1] = ADD32(SUB32(SUB32(s[i][1], s[i][2]), s[i][3]), bias);
                for (j = 0; j < 2; j++) {
                    int h = 2 * ty + i, w = 2 * t + j;
                    if (h < SIZE && w < SIZE) {
                        VF f = MINPS(MAXPS(MULPS(CVT(out[j]), multiplier), SETPS(-ZY)), SETPS(255 - ZY));
                        store_u8(&y[(h * SIZE + w) * CO + co], ADD32(CVTPS(f), SET1(ZY)));
                    }
                }
            }
        }
}

__attribute__((noinline)) void winograd_layer(const uint8_t *x, uint8_t *y)
{
    int ty;
    for (ty = 0; ty < TILES; ty++) {
        input_transform(x, ty);
        gemms();
        output_transform(y, ty);
    }
}

static void direct_reference(const uint8_t *x, const int8_t *w, const int32_t *b, const float *m, uint8_t *y)
{
    int h, wx, co, ci, i, j;
    for (h = 0; h < SIZE; h++)
        for (wx = 0; wx < SIZE; wx++)
            for (co = 0; co < CO; co++) {
                int32_t acc = b[co];
                float f;
                for (i = 0; i < 3; i++)
                    for (j = 0; j < 3; j++) {
                        int hh = h + i - 1, ww = wx + j - 1;
                        if (hh < 0 || hh >= SIZE || ww < 0 || ww >= SIZE) continue;
                        for (ci = 0; ci < CI; ci++) acc += (x[(hh * SIZE + ww) * CI + ci] - ZX) * w[((co * CI + ci) * 3 + i) * 3 + j];
                    }
                f = (float)acc * m[co];
                f = f < -ZY ? -ZY : f > 255 - ZY ? 255 - ZY : f;
                y[(h * SIZE + wx) * CO + co] = (uint8_t)((int)rintf(f) + ZY);
            }
}

int main(void)
{
    static int8_t w[CO * CI * 9];
    static int32_t b[CO];
    static float m[CO];
    static uint8_t x[SIZE * SIZE * CI], y[SIZE * SIZE * CO], expected[SIZE * SIZE * CO];
    int i, wrong = 0, inside = 0;
    srand(7);
    for (i = 0; i < CO * CI * 9; i++) w[i] = (int8_t)(rand() % 256 - 128); /* both ends of int8 */
    for (i = 0; i < SIZE * SIZE * CI; i++) x[i] = (uint8_t)(rand() % 256);
    for (i = 0; i < CO; i++) { /* scales that leave about half the outputs unsaturated */
        b[i] = rand() % 20001 - 10000;
        m[i] = (0.0005f + (float)(rand() % 1000) * 1e-6f) * 16.0f / (float)CI;
    }
    prepare(w, b, m);
    winograd_layer(x, y);
    direct_reference(x, w, b, m, expected);
    for (i = 0; i < SIZE * SIZE * CO; i++) {
        wrong += y[i] != expected[i];
        inside += expected[i] > 0 && expected[i] < 255;
    }
    printf("%d of %d outputs differ from the direct reference (%d unsaturated)\n", wrong, SIZE * SIZE * CO, inside);
    return wrong != 0;
}
