"""Layouts of the arrays the compiled kernels share: slots of the extended parameter vector, of the geometry
array, of the integrator settings and of the per-individual constants; the status codes; the columns of the
geometry table. Plain integers, no numba: every kernel module and the Python side (:mod:`toggle_id.simulate`,
:mod:`toggle_id.effects`) import them from here.
"""
from __future__ import annotations

# ---- layout of the extended parameter vector (names in toggle_id.params / toggle_id.effects) -------------
B_M, D_, J_M, K_I, K_L, K_T, L_Q, R_S, M2, M3, M5, MB, MC, MU, LAMBDA_D = range(15)
TAU_C, F_S, V_S, C_B, TAU_D, B_L, A_COG, N_COG, PHI_COG, F_LOAD, K3, S_SAT, X_OFF, C_KT = range(15, 29)
# the generic slider force of the discovery loop's catch-all check (not a library effect): piecewise-linear
# functions of slider B's speed and position on N_GEN uniform knots from *_LO to *_HI, weights *_W0 … (N)
N_GEN = 10
GV_LO, GV_HI = C_KT + 1, C_KT + 2
GV_W0 = GV_HI + 1
GX_LO, GX_HI = GV_W0 + N_GEN, GV_W0 + N_GEN + 1
GX_W0 = GX_HI + 1
# the generic error of the position reading, h(x_B measured), piecewise linear on N_GS uniform knots from GS_LO to
# GS_HI, weights GS_W0 … (m): an output map that toggle_id.discovery.model.Model adds; no kernel reads these slots
N_GS = 40
GS_LO, GS_HI = GX_W0 + N_GEN, GX_W0 + N_GEN + 1
GS_W0 = GS_HI + 1
N_THETA = GS_W0 + N_GS

# ---- layout of the geometry array (toggle_id.plant.Geometry.as_array) --------------------------------------
G_R1, G_R2, G_R3, G_R4, G_R5, G_H, G_PHI, G_P, G_Z, G_G, G_XBL, G_EPS = range(12)

# ---- status codes ----------------------------------------------------------------------------------------
OK, MODEL_FAILURE, SOLVER_FAILURE, INVALID_PARAMS = 0, 1, 2, 3

# ---- integrator settings array -----------------------------------------------------------------------------
# S_METHOD: 0 = DOPRI5 in both modes, 1 = DOPRI5 free / Rodas4 clamped, 2 = Rodas4 in both modes;
# S_STOPS: where steps end at every sample (toggle_id.kernels.stepping._next_stop): 0 = nowhere, 1 = on an input
# given by its samples, 2 = on any input
S_RTOL, S_ATOL_Q, S_ATOL_W, S_ATOL_I, S_H0, S_HMAX, S_MAXSTEPS, S_METHOD, S_STOPS = range(9)
METHOD_DOPRI5, METHOD_MIXED, METHOD_RODAS4 = 0, 1, 2
STOPS_NONE, STOPS_SAMPLED, STOPS_ALL = 0, 1, 2

# ---- per-individual constants (see _derived) ---------------------------------------------------------------
(PC_M0, PC_M3, PC_M5, PC_MB, PC_MC, PC_ZKT, PC_Z2BM, PC_FMU, PC_IEPS, PC_CB, PC_FLOAD, PC_KL, PC_D, PC_K3,
 PC_XBL, PC_KI, PC_ILQ, PC_RSL, PC_PLZL, PC_ULIM, PC_ZTAUC, PC_ZACOG, PC_NZ, PC_PHI, PC_FS, PC_IVS, PC_TAUD,
 PC_SA, PC_SB, PC_SW0, PC_SDW, PC_ST, PC_SIT, PC_SDWT, PC_T0, PC_IDT, PC_SWEEP, PC_XOFF, PC_CKT) = range(39)
# the generic slider force: on/off flag, knot origin and 1/spacing of speed and position, then the weights
PC_GEN, PC_GVLO, PC_GVIH, PC_GXLO, PC_GXIH = range(39, 44)
PC_GVW = 44
PC_GXW = PC_GVW + N_GEN
N_PC = PC_GXW + N_GEN

# ---- geometry table: cubic Hermite interpolation of the q-only functions, shared by all individuals ---------
# columns (value block, then derivative block): x_B, x_B', x_C', b3, b5, b3', b5', (x_B'²)', (x_C'²)', x_C
T_XB, T_DXB, T_DXC, T_B3, T_B5, T_DB3, T_DB5, T_DGB, T_DGC, T_XC = range(10)
N_TAB = 10
# header of the table array: q_lo, 1/dq, number of nodes
H_QLO, H_INVDQ, H_N, H_DQ = 0, 1, 2, 3
