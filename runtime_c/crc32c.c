/* CRC-32C (Castagnoli: reflected polynomial 0x82F63B78, initial value and final xor
 * 0xFFFFFFFF; crc32c("123456789") = 0xE3069283), the digest a posecorr model carries in
 * its metadata (docs/design.md, "Integrity"). It runs once per load over the file's
 * bytes, so a table of 16 entries, four bits a step (64 bytes of flash), serves better
 * than the 1 KB byte table: a 50 KB model costs well under a millisecond. */
#include "base.h"

static const uint32_t pc_crc32c_nibble[16] = {
    0x00000000u, 0x105EC76Fu, 0x20BD8EDEu, 0x30E349B1u, 0x417B1DBCu, 0x5125DAD3u,
    0x61C69362u, 0x7198540Du, 0x82F63B78u, 0x92A8FC17u, 0xA24BB5A6u, 0xB21572C9u,
    0xC38D26C4u, 0xD3D3E1ABu, 0xE330A81Au, 0xF36E6F75u,
};

uint32_t pc_crc32c(uint32_t crc, const void *data, size_t size)
{
    const uint8_t *p = (const uint8_t *)data;
    size_t i;
    crc = ~crc;
    for (i = 0; i < size; i++) {
        crc ^= p[i];
        crc = (crc >> 4) ^ pc_crc32c_nibble[crc & 15u];
        crc = (crc >> 4) ^ pc_crc32c_nibble[crc & 15u];
    }
    return ~crc;
}
