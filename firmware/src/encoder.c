/* The encoder's entry points for the ports (include/fw_encoder.h): the pins into the quadrature
 * count (src/quad.c), an illegal transition into the fault flags, and a captured edge time
 * into the renderer's edge history. Its own file so that the core (core.c) and the renderer
 * (render.c) do not call each other for the encoder. */
#include "fw.h"

void fw_encoder_pins(fw_t *f, uint8_t ab) {
    uint16_t before = f->quad.errors;
    fw_quad_update(&f->quad, ab);
    if (f->quad.errors != before) {
        f->faults |= HP_FAULT_ENCODER;
    }
}

void fw_encoder_edge(fw_t *f, uint8_t ab, uint32_t t_edge) {
    fw_encoder_pins(f, ab);
    fw_edges_track(&f->render.edges, f->quad.count, t_edge);
}
